#version 330
// Ground mesh of one cube -> output window. Positions are metres relative to the mesh centre
// (float32 keeps ~1e-6 relative precision, so keep them small); the centre's pixel position in the
// window is computed on the CPU in float64. Window pixel (col, row): col eastwards, row southwards,
// row 0 = north edge. NDC y = 2 row / height - 1 puts the north row at the framebuffer's first
// memory row, so the read-back is already north-up.
in vec2 in_pos;            // (E, N) metres relative to the mesh centre
in vec3 in_attr;           // (L line coordinate, s normalised sample coordinate, lambda ray depth)
uniform vec2 u_centre_px;  // (col, row) of the mesh centre in the window, pixels
uniform float u_inv_gsd;   // 1 / gsd, 1/m
uniform vec2 u_size;       // window (width, height), pixels
noperspective out float v_line;
noperspective out float v_ls;   // lambda * s
noperspective out float v_lam;  // lambda

void main() {
    vec2 px = vec2(u_centre_px.x + in_pos.x * u_inv_gsd, u_centre_px.y - in_pos.y * u_inv_gsd);
    gl_Position = vec4(2.0 * px / u_size - 1.0, 0.0, 1.0);
    v_line = in_attr.x;
    v_ls = in_attr.z * in_attr.y;
    v_lam = in_attr.z;
}
