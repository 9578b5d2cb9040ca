// Colour ramp, LOD colours and Lambert shading.
uniform vec3 sun;
uniform vec2 zrange;
uniform int lod_colour;
vec3 ramp(float h) {
    if (h < 0.0) {
        float t = clamp(-h / max(zrange.y, 1.0), 0.0, 1.0);
        return mix(vec3(0.25, 0.55, 0.85), vec3(0.05, 0.15, 0.45), sqrt(t));
    }
    float t = clamp((h - max(zrange.x, 0.0)) / max(zrange.y - max(zrange.x, 0.0), 1e-6), 0.0, 1.0);
    vec3 c0 = vec3(0.20, 0.45, 0.20), c1 = vec3(0.55, 0.65, 0.30), c2 = vec3(0.60, 0.45, 0.30);
    vec3 c3 = vec3(0.50, 0.45, 0.42), c4 = vec3(0.95, 0.95, 0.97);
    if (t < 0.25) return mix(c0, c1, t / 0.25);
    if (t < 0.55) return mix(c1, c2, (t - 0.25) / 0.30);
    if (t < 0.80) return mix(c2, c3, (t - 0.55) / 0.25);
    return mix(c3, c4, (t - 0.80) / 0.20);
}
vec3 level_colour(int lv) {
    float a = float(lv) * 0.618034;
    return 0.5 + 0.5 * cos(6.2831853 * (fract(a) + vec3(0.0, 0.33, 0.67)));
}
vec3 shade(vec3 n, float h, int lv) {
    vec3 base = ramp(h);
    if (lod_colour != 0) base = mix(base, level_colour(lv), 0.6);
    float lambert = max(dot(normalize(n), normalize(sun)), 0.0);
    return base * (0.35 + 0.65 * lambert);
}
