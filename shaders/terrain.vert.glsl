#version 330
// Terrain mesh of one cube -> output window: cube.vert.glsl plus the depth test's depth. Each
// vertex carries its distance from the camera (metres); depth = distance / u_far, so that where
// one line's triangles fold over each other on the map the nearest ground wins (GL_LESS).
// Positions are metres relative to the mesh centre; window pixel (col, row): col eastwards, row
// southwards, row 0 = north edge (see cube.vert.glsl).
in vec2 in_pos;            // (E, N) metres relative to the mesh centre
in vec3 in_attr;           // (L line coordinate, s normalised sample coordinate, lambda ray depth)
in float in_dist;          // distance from the camera to the vertex's ground point, metres
uniform vec2 u_centre_px;  // (col, row) of the mesh centre in the window, pixels
uniform float u_inv_gsd;   // 1 / gsd, 1/m
uniform vec2 u_size;       // window (width, height), pixels
uniform float u_far;       // larger than every distance, metres
noperspective out float v_line;
noperspective out float v_ls;   // lambda * s
noperspective out float v_lam;  // lambda

void main() {
    vec2 px = vec2(u_centre_px.x + in_pos.x * u_inv_gsd, u_centre_px.y - in_pos.y * u_inv_gsd);
    gl_Position = vec4(2.0 * px / u_size - 1.0, 2.0 * in_dist / u_far - 1.0, 1.0);
    v_line = in_attr.x;
    v_ls = in_attr.z * in_attr.y;
    v_lam = in_attr.z;
}
