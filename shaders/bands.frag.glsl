#version 330
// Pass 2 of the renderer: value = (DN - dark) * gain / response for up to 4 bands (8 with
// BANDS8: two RGBA fetches, two render targets) at the (line, sample) the lookup texture holds for
// this output pixel. Window pixel (col, row) = gl_FragCoord.xy - 0.5; row 0 = north edge.
// Uncovered pixels (line -1) get u_nan (a NaN set from the CPU, so that no compiler folds it);
// pixels whose line belongs to another line chunk are discarded.
#ifdef DN_FLOAT
uniform sampler2D u_dn;    // (lines, samples) texels of up to 4 bands, float
uniform sampler2D u_dn2;   // bands 5..8 (BANDS8)
#define DN_VEC vec4
#else
uniform usampler2D u_dn;   // (lines, samples) texels of up to 4 bands, R16UI..RGBA16UI
uniform usampler2D u_dn2;  // bands 5..8 (BANDS8)
#define DN_VEC uvec4
#endif
uniform isampler2D u_lookup;  // (window rows, window cols) texels (line, sample), RG32I
uniform sampler2D u_dark;  // (1, samples) float texels, one component per band
uniform sampler2D u_gain;  // (1, samples)
uniform sampler2D u_dark2; // bands 5..8 (BANDS8)
uniform sampler2D u_gain2;
uniform sampler2D u_resp;  // (1, u_hi - u_lo) response of each line, R32F
uniform int u_lo;          // first line held in u_dn (cube line index)
uniform int u_hi;          // one past the last line held in u_dn
uniform int u_bands;       // bands in this pass (1..4, or 1..8 with BANDS8)
uniform float u_sat;       // DN at or above this is saturated (use a huge value for none)
uniform float u_nan;       // NaN
layout(location = 0) out vec4 f_value;
#ifdef BANDS8
layout(location = 1) out vec4 f_value2;
layout(location = 2) out float f_sat;
#else
layout(location = 1) out float f_sat;
#endif

bool any_high(vec4 dnf, int first) {
    bvec4 used = lessThan(ivec4(first, first + 1, first + 2, first + 3), ivec4(u_bands));
    bvec4 high = greaterThanEqual(dnf, vec4(u_sat));
    return (used.x && high.x) || (used.y && high.y) || (used.z && high.z) || (used.w && high.w);
}

void main() {
    ivec2 index = texelFetch(u_lookup, ivec2(gl_FragCoord.xy), 0).xy;
    int line = index.x;
    if (line < 0) {
        f_value = vec4(u_nan);
#ifdef BANDS8
        f_value2 = vec4(u_nan);
#endif
        f_sat = 0.0;
        return;
    }
    if (line < u_lo || line >= u_hi) discard;
    int smp = index.y;
    int row = line - u_lo;
    float resp = texelFetch(u_resp, ivec2(row, 0), 0).r;
    vec4 dnf = vec4(texelFetch(u_dn, ivec2(smp, row), 0));
    f_value = (dnf - texelFetch(u_dark, ivec2(smp, 0), 0)) * texelFetch(u_gain, ivec2(smp, 0), 0) / resp;
    bool sat = any_high(dnf, 0);
#ifdef BANDS8
    vec4 dnf2 = vec4(texelFetch(u_dn2, ivec2(smp, row), 0));
    f_value2 = (dnf2 - texelFetch(u_dark2, ivec2(smp, 0), 0)) * texelFetch(u_gain2, ivec2(smp, 0), 0) / resp;
    sat = sat || any_high(dnf2, 4);
#endif
    f_sat = sat ? 1.0 : 0.0;
}
