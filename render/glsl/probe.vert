#version 450
#include "patch_vertex.glsl"
out float out_h;
out vec2 out_g;
void main() {
    Vtx v = make_vertex();
    out_h = v.masked > 0.0 ? MASKED_HEIGHT : v.h;
    out_g = vec2(v.g);
}
