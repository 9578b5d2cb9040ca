// The quadtree texture: node spheres, culling, the split flag, neighbours.
// CULL_MARGIN is #defined by the loader (geometry_splitting.gl.CULL_MARGIN).
#include "fetch.glsl"
layout(std430, binding = 4) readonly buffer Blocks { ivec4 blk[]; };
layout(std430, binding = 5) readonly buffer Quadtree { uvec2 qt[]; };
uniform float tau;
uniform vec2 viewport;
uniform vec2 slab;  // the terrain's (zmin, zmax)
// blk[4b] = (origin col, origin row, pool base, cap);
// blk[4b+1] = (quadtree offset, page, depth stored node by node, 1: a bitmask of infinite sigma follows);
// blk[4b+2] = neighbour block N, E, S, W (-1 none); blk[4b+3] = border caps N, E, S, W.

struct Sphere { vec3 c; float r; float sigma; };

Sphere node_sphere(ivec4 n) {
    int d = n.y;
    int dd = min(d, k - 1);
    // depths 0..top node by node, each deeper one as one entry per depth-top node
    // (geometry_splitting.pure.texture_nodes)
    int top = blk[4 * n.x + 1].z;
    int a = min(dd, top);
    int i = blk[4 * n.x + 1].x + ((1 << (2 * (a + 1))) - 1) / 3 - (1 << (2 * a))
            + max(dd - top, 0) * (1 << (2 * top)) + ((n.z >> (d - a)) << a) + (n.w >> (d - a));
    uvec2 q = qt[i];
    vec2 z = unpackHalf2x16(q.y);
    int s = 1 << (k - d);
    ivec2 g0 = blk[4 * n.x].xy + ivec2(n.w, n.z) * s;
    Sphere o;
    o.c = vec3((float(g0.x - cam_cell.x) + 0.5 * float(s)) * spacing.x - cam_frac.x,
               -(float(g0.y - cam_cell.y) + 0.5 * float(s)) * spacing.y - cam_frac.y,
               0.5 * (z.x + z.y) - cam_frac.z);
    o.r = 0.5 * float(s) * length(spacing) + 0.5 * (z.y - z.x);
    o.sigma = d < k ? uintBitsToFloat(q.x) : 0.0;
    if (d < k && dd > top && blk[4 * n.x + 1].w != 0) {
        // past `top` a block with nodata marks its nodes whose sigma is infinite in a bitmask after the
        // entries (geometry_splitting.pure.infinite_bits)
        int bit = ((1 << (2 * dd)) - (1 << (2 * (top + 1)))) / 3 + ((n.z >> (d - dd)) << dd)
                  + (n.w >> (d - dd));
        int entries = ((1 << (2 * (top + 1))) - 1) / 3 + (k - 1 - top) * (1 << (2 * top));
        uvec2 w = qt[blk[4 * n.x + 1].x + entries + (bit >> 6)];
        uint word = ((bit >> 5) & 1) == 0 ? w.x : w.y;
        if (((word >> uint(bit & 31)) & 1u) != 0u) o.sigma = uintBitsToFloat(0x7f800000u);
    }
    return o;
}

// Culling sphere: the node's column through the terrain's height range.
Sphere cull_sphere(ivec4 n) {
    int s = 1 << (k - n.y);
    ivec2 g0 = blk[4 * n.x].xy + ivec2(n.w, n.z) * s;
    Sphere o;
    o.c = vec3((float(g0.x - cam_cell.x) + 0.5 * float(s)) * spacing.x - cam_frac.x,
               -(float(g0.y - cam_cell.y) + 0.5 * float(s)) * spacing.y - cam_frac.y,
               0.5 * (slab.x + slab.y) - cam_frac.z);
    o.r = 0.5 * float(s) * length(spacing) + 0.5 * (slab.y - slab.x);
    o.sigma = 0.0;
    return o;
}

bool visible(ivec4 n) {
    Sphere o = cull_sphere(n);
    vec4 w = vec4(mvp[0][3], mvp[1][3], mvp[2][3], mvp[3][3]);
    for (int i = 0; i < 3; i++) {
        vec4 a = vec4(mvp[0][i], mvp[1][i], mvp[2][i], mvp[3][i]);
        for (int sg = -1; sg <= 1; sg += 2) {
            vec4 p = w + float(sg) * a;
            float dist = (dot(p.xyz, o.c) + p.w) / length(p.xyz);
            if (dist < -o.r * (1.0 + CULL_MARGIN)) return false;
        }
    }
    return true;
}

float projected(Sphere o, int d) {
    float h = 0.5 * float(1 << (k - d));
    vec2 off[5] = vec2[5](vec2(0.0), vec2(h, 0.0), vec2(-h, 0.0), vec2(0.0, h), vec2(0.0, -h));
    float rho = 0.0;
    for (int i = 0; i < 5; i++) {
        vec3 p = o.c + vec3(off[i] * spacing, 0.0);
        vec4 a = mvp * vec4(p, 1.0);
        vec4 b = mvp * vec4(p + vec3(0.0, 0.0, o.sigma), 1.0);
        if (a.w <= 0.0 || b.w <= 0.0) return uintBitsToFloat(0x7f800000u);
        rho = max(rho, length(viewport * (b.xy / b.w - a.xy / a.w)));
    }
    return rho;
}

bool flag(Sphere o, int d) {
    if (isinf(o.sigma)) return true;  // the node holds valid and masked samples: refine
    if (length(o.c) - o.r < 0.0) return o.sigma != 0.0;
    return tau <= projected(o, d);
}

int lead(int v, int d, bool ones) {
    int x = (ones ? ~v : v) & ((1 << d) - 1);
    return x == 0 ? d : d - 1 - findMSB(x);
}

bool allowed(ivec4 n) {
    int d = n.y;
    if (d >= blk[4 * n.x].w) return false;
    ivec4 bc = blk[4 * n.x + 3];
    return lead(n.z, d, false) < bc.x && lead(n.w, d, true) < bc.y
        && lead(n.z, d, true) < bc.z && lead(n.w, d, false) < bc.w;
}

bool splits(ivec4 n) { return allowed(n) && flag(node_sphere(n), n.y); }

// The depth-e node across edge dir of leaf L next to the edge sample s (from L's corner).
ivec4 beside(ivec4 L, int dir, int s, int e) {
    int S = 1 << (k - L.y);
    ivec2 p0 = ivec2(L.w, L.z) * S;
    ivec2 q = dir == 0 ? p0 + ivec2(s, -1) : dir == 1 ? p0 + ivec2(S, s)
            : dir == 2 ? p0 + ivec2(s, S) : p0 + ivec2(-1, s);
    int sh = k - e, m = (1 << e) - 1;
    int c = q.x >> sh, r = q.y >> sh;
    int b = L.x;
    if (r < 0 || r > m || c < 0 || c > m) {
        b = blk[4 * L.x + 2][dir];
        r &= m;
        c &= m;
    }
    return ivec4(b, e, r, c);
}

// N (same depth as leaf L) is a node of the expanded tree.
bool exists_beside(ivec4 N, ivec4 L) {
    if (N.x < 0 || !visible(N)) return false;
    for (int j = N.y - 1; j >= 0; j--) {
        int sh = N.y - j;
        ivec4 a = ivec4(N.x, j, N.z >> sh, N.w >> sh);
        if (N.x == L.x && a.z == (L.z >> sh) && a.w == (L.w >> sh)) return true;
        if (!splits(a)) return false;
    }
    return true;
}
