#version 450
#include "chunk_vertex.glsl"
out vec3 t_gh;
void main() {
    Vtx v = tess_vertex();
    t_gh = vec3(vec2(v.g), v.masked > 0.0 ? MASKED_HEIGHT : v.h);
    gl_Position = vec4(0.0);
}
