#version 330
// Pass 1 of the renderer: which (line, sample) of the cube each output pixel centre sees.
// Same coverage and indexing rules as the band pass used to apply while drawing the mesh:
// line = floor(L + 0.5), discarded outside [u_lo, u_hi) (opening / closing rows belong to the
// neighbouring cubes); sample = clamp(floor(samples * s), 0, samples - 1), s perspective-correct:
// (lambda s) / lambda, both interpolated without perspective (see archive/render/mesh.py).
// Written as floats (exact for integers below 2^24) into an RG32F target cleared to -1: a float
// target clears with plain glClear, which is undefined for integer targets.
// With COUNT defined the same coverage rule writes (1, 0) instead, drawn with additive blending:
// how many layers of the mesh (passes, folds at turns) cover each pixel centre.
uniform int u_lo;          // first line of the cube this draw may write (0)
uniform int u_hi;          // one past the last (lines)
uniform int u_samples;
noperspective in float v_line;
noperspective in float v_ls;
noperspective in float v_lam;
layout(location = 0) out vec2 f_index;  // (line, sample)

void main() {
    int line = int(floor(v_line + 0.5));
    if (line < u_lo || line >= u_hi) discard;
#ifdef COUNT
    f_index = vec2(1.0, 0.0);
#else
    int smp = clamp(int(floor(float(u_samples) * v_ls / v_lam)), 0, u_samples - 1);
    f_index = vec2(float(line), float(smp));
#endif
}
