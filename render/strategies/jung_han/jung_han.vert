#version 450
#include "fetch.glsl"
in ivec4 in_a;   // block origin (global col, row), vertex (col, row) in the block
in ivec4 in_b;   // slot base, drawn level, 0, 0
in float in_h;   // drawn (possibly height-adjusted) height - the store's reference height
Vtx jh_vertex() {
    Vtx v = vertex_at(in_a, in_b, 0, 0);
    if (v.masked == 0.0) {
        v.h = in_h;
        v.rel.z = in_h - cam_z;
    }
    return v;
}
#include "emit.glsl"
void main() { emit(jh_vertex()); }
