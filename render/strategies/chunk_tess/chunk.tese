#version 450
#include "chunk_vertex.glsl"
#include "emit.glsl"
void main() { emit(tess_vertex()); }
