#version 450
#include "quadtree.glsl"
layout(points) in;
layout(points, max_vertices = 2) out;
flat in ivec4 v_a[];
flat in ivec4 v_b[];
flat out ivec4 o_leaf;
flat out ivec4 o_tri;
void main() {
    ivec4 L = v_a[0], t = v_b[0];
    o_leaf = L;
    if ((t.x & 16) == 0) { o_tri = t; EmitVertex(); EndPrimitive(); return; }
    int dir = t.x & 15, e = t.z + 1, half_len = 1 << (k - e);
    for (int h = 0; h < 2; h++) {
        int s = t.y + h * half_len;
        ivec4 N = beside(L, dir, s, e);
        bool p = N.x >= 0 && visible(N) && splits(N);
        o_tri = ivec4(dir | (p ? 16 : 0), s, e, 0);
        EmitVertex();
        EndPrimitive();
    }
}
