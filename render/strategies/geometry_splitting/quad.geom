#version 450
#include "quadtree.glsl"
layout(points) in;
layout(points, max_vertices = 4) out;
layout(std430, binding = 7) buffer Stats { int stats[4]; };
flat in ivec4 v_a[];
flat out ivec4 o_leaf;
flat out ivec4 o_tri;
void main() {
    ivec4 L = ivec4(v_a[0].x, v_a[0].y & 255, v_a[0].z, v_a[0].w);
    int d = L.y;
    if (d < k && !allowed(L) && flag(node_sphere(L), d)) atomicAdd(stats[0], 1);
    atomicMax(stats[1], d);
    atomicMin(stats[2], d);
    bool fine[4];
    bool any = false;
    for (int dir = 0; dir < 4; dir++) {
        ivec4 N = beside(L, dir, 0, d);
        fine[dir] = d < k && exists_beside(N, L) && splits(N);
        any = any || fine[dir];
    }
    o_leaf = L;
    if (!any) {
        o_tri = ivec4(4, 0, d, 0); EmitVertex(); EndPrimitive();
        o_tri = ivec4(5, 0, d, 0); EmitVertex(); EndPrimitive();
    } else {
        for (int dir = 0; dir < 4; dir++) {
            o_tri = ivec4(dir | (fine[dir] ? 16 : 0), 0, d, 0);
            EmitVertex();
            EndPrimitive();
        }
    }
}
