#version 450
#include "seam_vertex.glsl"
#include "emit.glsl"
void main() { emit(seam_vertex()); }
