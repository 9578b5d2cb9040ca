#version 450
#include "pull.glsl"
#include "emit.glsl"
void main() {
    bool ok;
    Vtx v = pull(ok);
    emit(v);
    if (!ok) gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
