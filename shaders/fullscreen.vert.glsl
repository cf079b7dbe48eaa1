#version 330
// One triangle that covers the whole viewport (vertices from gl_VertexID, no attributes):
// every fragment of the window runs the band pass once.
void main() {
    vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
