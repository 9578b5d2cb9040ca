#version 450
#include "patch_vertex.glsl"
#include "emit.glsl"
void main() { emit(make_vertex()); }
