#version 450
#include "pull.glsl"
out vec4 t_out;
void main() {
    bool ok;
    Vtx v = pull(ok);
    t_out = vec4(vec2(v.g), v.masked > 0.0 ? MASKED_HEIGHT : v.h, ok ? 1.0 : 0.0);
    gl_Position = vec4(0.0);
}
