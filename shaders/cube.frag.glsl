#version 330
// One pass of up to 4 bands: value = (DN - dark) * gain / response.
// Line index = floor(L + 0.5): each line's span is centred on its mid-exposure row. Lines outside
// [u_lo, u_hi) belong to a neighbouring cube (opening / closing rows) or another chunk: discarded.
// Sample index = floor(samples * s), s perspective-correct: (lambda s) / lambda, both interpolated
// without perspective (see archive/render/mesh.py).
#ifdef DN_FLOAT
uniform sampler2D u_dn;    // (lines, samples) texels of up to 4 bands, float
#define DN_VEC vec4
#else
uniform usampler2D u_dn;   // (lines, samples) texels of up to 4 bands, R16UI..RGBA16UI
#define DN_VEC uvec4
#endif
uniform sampler2D u_dark;  // (1, samples) float texels, one component per band
uniform sampler2D u_gain;  // (1, samples)
uniform sampler2D u_resp;  // (1, u_hi - u_lo) response of each line, R32F
uniform int u_lo;          // first line held in u_dn (cube line index)
uniform int u_hi;          // one past the last line held in u_dn
uniform int u_samples;
uniform int u_bands;       // bands in this pass (1..4)
uniform float u_sat;       // DN at or above this is saturated (use a huge value for none)
noperspective in float v_line;
noperspective in float v_ls;
noperspective in float v_lam;
layout(location = 0) out vec4 f_value;
layout(location = 1) out vec2 f_flags;  // (covered, saturated)

void main() {
    int line = int(floor(v_line + 0.5));
    if (line < u_lo || line >= u_hi) discard;
    int smp = clamp(int(floor(float(u_samples) * v_ls / v_lam)), 0, u_samples - 1);
    int row = line - u_lo;
    DN_VEC dn = texelFetch(u_dn, ivec2(smp, row), 0);
    vec4 dnf = vec4(dn);
    vec4 dark = texelFetch(u_dark, ivec2(smp, 0), 0);
    vec4 gain = texelFetch(u_gain, ivec2(smp, 0), 0);
    float resp = texelFetch(u_resp, ivec2(row, 0), 0).r;
    f_value = (dnf - dark) * gain / resp;
    bvec4 used = lessThan(ivec4(0, 1, 2, 3), ivec4(u_bands));
    bvec4 high = greaterThanEqual(dnf, vec4(u_sat));
    bool sat = (used.x && high.x) || (used.y && high.y) || (used.z && high.z) || (used.w && high.w);
    f_flags = vec2(1.0, sat ? 1.0 : 0.0);
}
