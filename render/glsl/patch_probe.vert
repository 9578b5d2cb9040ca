#version 450
// Qiu's patch vertices for the triangle read-back (triangle_probe.geom): global (col, row)
// and the fetched height (relative to the store's reference height; MASKED_HEIGHT if masked).
#include "patch_vertex.glsl"
out vec3 t_gh;
void main() {
    Vtx v = make_vertex();
    t_gh = vec3(vec2(v.g), v.masked > 0.0 ? MASKED_HEIGHT : v.h);
    gl_Position = vec4(0.0);
}
