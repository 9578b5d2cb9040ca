#version 450
in vec3 g_normal;
in float g_h;
in float g_masked;
flat in int g_level;
noperspective in vec3 g_dist;
out vec4 f_colour;
#include "shade.glsl"
#include "depth.glsl"
void main() {
    if (g_masked > 0.0) discard;
    write_depth();
    vec3 c = shade(g_normal, g_h, g_level);
    float d = min(g_dist.x, min(g_dist.y, g_dist.z));
    float edge = 1.0 - smoothstep(0.0, 1.0, d);
    f_colour = vec4(mix(c, vec3(0.05), edge * 0.8), 1.0);
}
