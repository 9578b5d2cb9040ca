// Qiu's CLOD patch grid with edge snapping: make_vertex().
#include "fetch.glsl"

in ivec2 in_grid;
in ivec4 in_a;
in ivec4 in_b;

Vtx make_vertex() {
    int c = in_b.z;
    int n = 1 << c;
    int ci = in_grid.x >> (patch_log2 - c);
    int cj = in_grid.y >> (patch_log2 - c);
    int tn = in_b.w & 15, te = (in_b.w >> 4) & 15;
    int ts = (in_b.w >> 8) & 15, tw = (in_b.w >> 12) & 15;
    int si = ci, sj = cj;
    if (cj == 0 && tn > 0) si = (ci >> tn) << tn;
    if (cj == n && ts > 0) si = (ci >> ts) << ts;
    if (ci == 0 && tw > 0) sj = (cj >> tw) << tw;
    if (ci == n && te > 0) sj = (cj >> te) << te;
    return vertex_at(in_a, in_b, si, sj);
}
