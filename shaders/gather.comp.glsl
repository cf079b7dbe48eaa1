#version 430
// Pass 2 of the renderer as a GL compute shader (archive/render/compute.py): for each output pixel
// of the dispatch, the flat index line * samples + sample it sees (the CPU gather's index,
// archive/render/renderer.py GatherIndex; u_plane where no line covers it) selects one DN per band,
// value = ((float(DN) - dark) * gain) / response, in that order, each operation rounded to float32
// and never contracted into an FMA (precise): the CPU gather's operations, so the same values.
// One invocation per pixel computes the u_bands bands of the dispatch (band-major output: the
// bands' planes as the caller's (band, row, col) array holds them). Uncovered pixels get u_nan.
// Pixel p of the dispatch is pixel u_first + p of the covered rows the index holds (outside
// [0, u_covered): rows above or below every covered row, NaN too).
#ifndef LOCAL
#define LOCAL 256
#endif
layout(local_size_x = LOCAL) in;

layout(std430, binding = 0) readonly buffer Index { int index[]; };  // covered rows, row-major
#ifdef DN_FLOAT
layout(std430, binding = 1) readonly buffer Dn { float dn[]; };      // (bands, lines, samples)
#else
// uint16 (bands, lines, samples), 2 per word, little-endian (element 2k in the low half)
layout(std430, binding = 1) readonly buffer Dn { uint dn_words[]; };
#endif
layout(std430, binding = 2) readonly buffer Dark { float dark[]; };  // (bands, samples)
layout(std430, binding = 3) readonly buffer Gain { float gain[]; };  // (bands, samples)
layout(std430, binding = 4) readonly buffer Resp { float resp[]; };  // (lines,)
layout(std430, binding = 5) writeonly buffer Values { float values[]; };  // (bands, pixels)

uniform int u_pixels;   // pixels of this dispatch
uniform int u_first;    // index entry of the dispatch's first pixel (negative: rows above the covered ones)
uniform int u_covered;  // index entries (covered rows x width)
uniform int u_bands;    // bands of this dispatch
uniform int u_samples;  // samples per line of the cube
uniform int u_plane;    // lines * samples: one band's DN, and the index of "not covered"
uniform float u_nan;    // NaN, set from the CPU (0x7fc00000, numpy's NaN) so no compiler folds it

void main() {
    int p = int(gl_GlobalInvocationID.y * gl_NumWorkGroups.x * uint(LOCAL) + gl_GlobalInvocationID.x);
    if (p >= u_pixels) return;
    int q = u_first + p;
    int at = (q >= 0 && q < u_covered) ? index[q] : u_plane;
    if (at < 0 || at >= u_plane) {
        for (int b = 0; b < u_bands; ++b) values[b * u_pixels + p] = u_nan;
        return;
    }
    int line = at / u_samples;
    int smp = at - line * u_samples;
    float r = resp[line];
    for (int b = 0; b < u_bands; ++b) {
#ifdef DN_FLOAT
        float d = dn[b * u_plane + at];
#else
        uint e = uint(b) * uint(u_plane) + uint(at);
        float d = float((dn_words[e >> 1] >> ((e & 1u) << 4)) & 0xFFFFu);
#endif
        int k = b * u_samples + smp;
        precise float v = ((d - dark[k]) * gain[k]) / r;
        values[b * u_pixels + p] = v;
    }
}
