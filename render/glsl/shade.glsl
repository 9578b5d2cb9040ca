// Colour ramp, LOD colours and Lambert shading.
uniform vec3 sun;
uniform vec4 ramp_map;  // land offset, land scale, sea scale, sea level (render.frame.ramp_map)
uniform int lod_colour;
// Hypsometric ramp over the DEM's height range; sea colours below 0 only when that range
// crosses 0 (ramp_map.z > 0); a constant DEM has scale 0: one colour, no stripes. Heights are
// relative to the store's reference height (render.frame.FrameServices.zref).
vec3 ramp(float h) {
    if (ramp_map.z > 0.0 && h < ramp_map.w) {
        float t = clamp((ramp_map.w - h) * ramp_map.z, 0.0, 1.0);
        return mix(vec3(0.25, 0.55, 0.85), vec3(0.05, 0.15, 0.45), sqrt(t));
    }
    float t = clamp((h - ramp_map.x) * ramp_map.y, 0.0, 1.0);
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
