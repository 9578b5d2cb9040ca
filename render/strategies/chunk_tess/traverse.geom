#version 450
// One traversal pass: a node (block, depth | done << 8, row, col) with its 4 neighbour-level
// channels (N, E, S, W) either splits into its visible children (which inherit the channels on
// the parent's outer edges) or is marked done (unset channels get its own level); done nodes
// are carried through.
#include "traverse.glsl"
layout(points) in;
layout(points, max_vertices = 4) out;
layout(std430, binding = 7) buffer Stats { int stats[8]; };
uniform int cull_input;
flat in ivec4 v_a[];
flat in ivec4 v_b[];
flat out ivec4 o_a;
flat out ivec4 o_b;
void main() {
    ivec4 n = v_a[0], ch = v_b[0];
    int d = n.y & 255;
    ivec4 m = ivec4(n.x, d, n.z, n.w);
    if (cull_input != 0 && !visible(m)) return;
    if ((n.y >> 8) != 0) { o_a = n; o_b = ch; EmitVertex(); EndPrimitive(); return; }
    for (int dir = 0; dir < 4; dir++) {  // the virtual same-depth neighbours
        if (ch[dir] != UNSET) continue;
        ivec4 N = beside(m, dir);
        if (N.x < 0 || !visible(N)) ch[dir] = NONE;
        else if (!splits(N)) ch[dir] = level_of(N);
    }
    bool want = refinable(m) && wants(m);
    if (!(want && allowed(m))) {
        if (want) atomicAdd(stats[0], 1);  // clamped by the resident level
        for (int dir = 0; dir < 4; dir++) if (ch[dir] == UNSET) ch[dir] = level_of(m);
        o_a = ivec4(n.x, d | 256, n.z, n.w);
        o_b = ch;
        EmitVertex();
        EndPrimitive();
        return;
    }
    for (int i = 0; i < 4; i++) {
        int cr = i >> 1, cc = i & 1;
        ivec4 c = ivec4(n.x, d + 1, 2 * n.z + cr, 2 * n.w + cc);
        if (!visible(c)) continue;
        o_a = c;
        o_b = ivec4(cr == 0 ? ch.x : UNSET, cc == 1 ? ch.y : UNSET,
                    cr == 1 ? ch.z : UNSET, cc == 0 ? ch.w : UNSET);
        EmitVertex();
        EndPrimitive();
    }
}
