// The varyings every strategy's last vertex stage hands to the shared fragment shader.
out vec3 v_normal;
out float v_h;
out float v_masked;
flat out int v_level;
void emit(Vtx v) {
    gl_Position = mvp * vec4(v.rel, 1.0);
    v_normal = v.normal;
    v_h = v.h;
    v_masked = v.masked;
    v_level = v.level;
}
