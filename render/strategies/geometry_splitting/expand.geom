#version 450
#include "quadtree.glsl"
layout(points) in;
layout(points, max_vertices = 4) out;
uniform int cull_input;
flat in ivec4 v_a[];
flat out ivec4 o_node;
void main() {
    ivec4 n = v_a[0];
    int d = n.y & 255;
    ivec4 m = ivec4(n.x, d, n.z, n.w);
    if (cull_input != 0 && !visible(m)) return;
    if ((n.y >> 8) == 0 && splits(m)) {
        for (int i = 0; i < 4; i++) {
            ivec4 c = ivec4(n.x, d + 1, 2 * n.z + (i >> 1), 2 * n.w + (i & 1));
            if (visible(c)) { o_node = c; EmitVertex(); EndPrimitive(); }
        }
    } else {
        o_node = ivec4(n.x, d | 256, n.z, n.w);
        EmitVertex();
        EndPrimitive();
    }
}
