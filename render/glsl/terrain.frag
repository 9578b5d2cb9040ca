#version 450
in vec3 v_normal;
in float v_h;
in float v_masked;
flat in int v_level;
uniform int show_holes;  // 1: draw the nodata holes' triangles too (the crack count's check)
out vec4 f_colour;
#include "shade.glsl"
#include "depth.glsl"
void main() {
    if (v_masked > 0.0 && show_holes == 0) discard;
    write_depth();
    f_colour = vec4(shade(v_normal, v_h, v_level), 1.0);
}
