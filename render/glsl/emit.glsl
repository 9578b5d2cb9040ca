// The varyings every strategy's last vertex stage hands to the shared fragment shader, and
// the nodata clip: a masked vertex is at clip distance -1, a terrain vertex at 0, so (with
// GL_CLIP_DISTANCE0 on: FrameServices.timed_frame) a triangle with a masked corner is clipped
// to its terrain edge or corner, which has no area: no fragment at all. (The fragment
// shader's discard of an interpolated v_masked > 0 alone lets through pixels whose centres lie
// on such a triangle's terrain edge, where v_masked is 0.) show_holes (the crack check's
// holes drawn too): no clip (Mesa llvmpipe clips by a written gl_ClipDistance even when
// GL_CLIP_DISTANCE0 is off, so the uniform, not only the enable, decides).
uniform int show_holes;
out vec3 v_normal;
out float v_h;
out float v_masked;
flat out int v_level;
void emit(Vtx v) {
    gl_Position = mvp * vec4(v.rel, 1.0);
    gl_ClipDistance[0] = v.masked > 0.0 && show_holes == 0 ? -1.0 : 0.0;
    v_normal = v.normal;
    v_h = v.h;
    v_masked = v.masked;
    v_level = v.level;
}
