#version 330
// Pass 2 of the renderer: value = (DN - dark) * gain / response for NOUT bands (1..8, one R32F
// render target each) at the (line, sample) the lookup texture holds for this output pixel.
// DN come from up to two RGBA textures, 4 bands per texel fetch (u_dn0: bands 1-4, u_dn1: bands
// 5-8 of the pass); dark and gain likewise. Window pixel (col, row) = gl_FragCoord.xy - 0.5;
// row 0 = north edge. Uncovered pixels (line -1) get u_nan (a NaN set from the CPU, so that no
// compiler folds it); pixels whose line belongs to another line chunk are discarded.
// Saturation is flagged on the CPU from the same lookup (archive/render/renderer.py).
#ifndef NOUT
#define NOUT 8
#endif
#ifdef DN_FLOAT
uniform sampler2D u_dn0;   // (samples, lines) texels of 4 bands, RGBA32F
uniform sampler2D u_dn1;
#else
uniform usampler2D u_dn0;  // (samples, lines) texels of 4 bands, RGBA16UI
uniform usampler2D u_dn1;
#endif
uniform isampler2D u_lookup;  // (window cols, window rows) texels (line, sample), RG32I
uniform sampler2D u_dark0;    // (samples, 1) RGBA32F, bands 1-4 of the pass
uniform sampler2D u_gain0;
uniform sampler2D u_dark1;    // bands 5-8
uniform sampler2D u_gain1;
uniform sampler2D u_resp;     // (u_hi - u_lo, 1) response of each line, R32F
uniform int u_lo;             // first line held in the DN textures (cube line index)
uniform int u_hi;             // one past the last line held
uniform float u_nan;          // NaN
layout(location = 0) out float f_value[NOUT];

void main() {
    ivec2 index = texelFetch(u_lookup, ivec2(gl_FragCoord.xy), 0).xy;
    int line = index.x;
    if (line < 0) {
        for (int b = 0; b < NOUT; ++b) f_value[b] = u_nan;
        return;
    }
    if (line < u_lo || line >= u_hi) discard;
    ivec2 at = ivec2(index.y, line - u_lo);
    ivec2 col = ivec2(index.y, 0);
    float resp = texelFetch(u_resp, ivec2(at.y, 0), 0).r;
    vec4 v0 = (vec4(texelFetch(u_dn0, at, 0)) - texelFetch(u_dark0, col, 0)) * texelFetch(u_gain0, col, 0) / resp;
#if NOUT > 4
    vec4 v1 = (vec4(texelFetch(u_dn1, at, 0)) - texelFetch(u_dark1, col, 0)) * texelFetch(u_gain1, col, 0) / resp;
#endif
    for (int b = 0; b < NOUT; ++b) {
#if NOUT > 4
        f_value[b] = b < 4 ? v0[b] : v1[b - 4];
#else
        f_value[b] = v0[b];
#endif
    }
}
