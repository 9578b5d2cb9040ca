#version 450
// The chunks of one height page as the tessellation draw's vertices (FrameServices.instances'
// layout: block origin, node origin, pool base, level, cells, snaps N | E | S | W).
// snap = max(0, level - neighbour level), at most the chunk's cells; stats: clamped,
// violations, triangles, max level, min level.
#include "traverse.glsl"
layout(points) in;
layout(points, max_vertices = 1) out;
layout(std430, binding = 7) buffer Stats { int stats[8]; };
uniform int page;
uniform int stitch;
flat in ivec4 v_a[];
flat in ivec4 v_b[];
flat out ivec4 o_a;
flat out ivec4 o_b;
void main() {
    ivec4 n = ivec4(v_a[0].x, v_a[0].y & 255, v_a[0].z, v_a[0].w);
    ivec4 b0 = blk[4 * n.x];
    if (blk[4 * n.x + 1].y != page) return;
    int lv = level_of(n), cells = lv - n.y, snaps = 0, outer = 0;
    for (int dir = 0; dir < 4; dir++) {
        int ln = v_b[0][dir];
        if (ln >= 0 && ln < n.y) atomicAdd(stats[1], 1);  // neighbour spacing > the edge
        int t = (ln < 0 || stitch == 0) ? 0 : clamp(lv - ln, 0, cells);
        snaps |= t << (4 * dir);
        outer += 1 << (cells - t);
    }
    int q = (1 << cells) - 2;
    atomicAdd(stats[2], cells == 0 ? 2 : 2 * q * q + 4 * q + outer);
    atomicMax(stats[3], lv);
    atomicMin(stats[4], lv);
    int e = 1 << (k - n.y);
    o_a = ivec4(b0.x, b0.y, n.w * e, n.z * e);
    o_b = ivec4(b0.z, lv, cells, snaps);
    EmitVertex();
    EndPrimitive();
}
