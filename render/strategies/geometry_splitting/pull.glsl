// Vertex pulling: triangle i = records 2i (leaf) and 2i+1 (kind | pending, seg start, seg depth).
#include "quadtree.glsl"
layout(std430, binding = 6) readonly buffer Tris { ivec4 tris[]; };
uniform int page;

Vtx fetch_vertex(int b, ivec2 p, int lv) {
    // p: block-local sample of block b on the level-lv grid
    int sh = k - lv;
    ivec4 a = ivec4(blk[4 * b].xy, 0, 0);
    return vertex_at(a, ivec4(blk[4 * b].z, lv, 0, 0), p.x >> sh, p.y >> sh);
}

Vtx pull(out bool ok) {
    int id = gl_VertexID / 3, j = gl_VertexID % 3;
    ivec4 L = tris[2 * id], t = tris[2 * id + 1];
    int b = L.x, d = L.y, kind = t.x & 15;
    ok = blk[4 * b + 1].y == page;
    int S = 1 << (k - d);
    ivec2 p0 = ivec2(L.w, L.z) * S;
    int cap = blk[4 * b].w;
    Vtx v;
    if (kind >= 4) {
        ivec2 c[3] = kind == 4 ? ivec2[3](ivec2(0, 0), ivec2(S, 0), ivec2(S, S))
                               : ivec2[3](ivec2(0, 0), ivec2(S, S), ivec2(0, S));
        v = fetch_vertex(b, p0 + c[j], d);
    } else if (j == 2) {
        if (d + 1 <= cap) {
            v = fetch_vertex(b, p0 + ivec2(S / 2), d + 1);
        } else {
            Vtx va = fetch_vertex(b, p0, d), vd = fetch_vertex(b, p0 + ivec2(S), d);
            v = va;
            v.rel = 0.5 * (va.rel + vd.rel);
            v.h = 0.5 * (va.h + vd.h);
            v.masked = max(va.masked, vd.masked);
            v.normal = normalize(va.normal + vd.normal);
            v.g = (va.g + vd.g) / 2;
        }
    } else {
        int e = t.z;
        int s = t.y + j * (1 << (k - e));
        ivec2 q = kind == 0 ? ivec2(s, 0) : kind == 1 ? ivec2(S, s)
                : kind == 2 ? ivec2(s, S) : ivec2(0, s);
        ivec2 p = p0 + q;
        if (e <= cap) {
            v = fetch_vertex(b, p, e);
        } else {
            int nb = blk[4 * b + 2][kind];
            v = fetch_vertex(nb, p + blk[4 * b].xy - blk[4 * nb].xy, e);
        }
    }
    v.level = d;
    return v;
}
