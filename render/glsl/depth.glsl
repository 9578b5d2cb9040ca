// Logarithmic depth (docs/RENDER.md, "Precision and extremes"): the fragment's eye distance
// along the view axis (1 / gl_FragCoord.w) mapped by log2 from [near, far] onto [0, 1], so a
// near plane of centimetres and a far plane of 1,000 km share one 24-bit depth buffer
// (relative depth resolution ~ log2(far / near) / 2^24 at every distance).
uniform vec2 depth_log;  // near, 1 / log2(far / near)
void write_depth() {
    float w = max(1.0 / gl_FragCoord.w, depth_log.x);
    gl_FragDepth = clamp(log2(w / depth_log.x) * depth_log.y, 0.0, 1.0);
}
