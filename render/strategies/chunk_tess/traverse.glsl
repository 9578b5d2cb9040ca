// Kim, Lee & Shin's chunk traversal on the GPU (CPU twin: render.select.select_patches with
// kim_metric + stitch): node spheres, the frustum-hull disc cull, the chunk split test and the
// same-depth neighbours.
#include "fetch.glsl"
layout(std430, binding = 4) readonly buffer Blocks { ivec4 blk[]; };
layout(std430, binding = 5) readonly buffer Deltas { float eps[]; };
uniform float tau;
uniform vec2 viewport;
uniform int chunk;        // c: a node draws 2**c cells of level min(k, depth + c)
uniform int start_depth;  // nodes shallower than this split whatever their error
uniform int n_poly;       // vertices of the frustum's ground hull (0: no culling)
uniform int poly_ccw;     // the hull has positive area
uniform vec2 poly[32];    // the hull, camera-relative (x, y); gpu.MAX_HULL
// blk[4b] = (origin col, origin row, pool base, cap); blk[4b+1] = (delta offset, page,
// window rows, window cols); blk[4b+2] = neighbour block N, E, S, W (-1 none);
// blk[4b+3] = (zmin, zmax) float bits, 0, 0.
const int UNSET = -2;   // channel: the neighbour at this depth splits (not known yet)
const int NONE = -1;    // channel: no neighbour (terrain edge, block not drawn, culled)

vec2 centre_xy(ivec4 n) {
    int s = 1 << (k - n.y);
    ivec2 g0 = blk[4 * n.x].xy + ivec2(n.w, n.z) * s;
    return vec2((float(g0.x - cam_cell.x) + 0.5 * float(s)) * spacing.x - cam_frac.x,
                -(float(g0.y - cam_cell.y) + 0.5 * float(s)) * spacing.y - cam_frac.y);
}

float half_diagonal(int d) { return 0.5 * float(1 << (k - d)) * length(spacing); }

// streamer.frustum.polygon_meets_circles (render.select.DiscCull) for the node's disc.
bool meets_hull(vec2 c, float r) {
    float dist2 = uintBitsToFloat(0x7f800000u);
    bool inside = true;
    for (int i = 0; i < n_poly; i++) {
        vec2 p = poly[i], e = poly[(i + 1) % n_poly] - p, a = c - p;
        float ee = dot(e, e);
        float t = ee > 0.0 ? clamp(dot(a, e) / ee, 0.0, 1.0) : 0.0;
        vec2 q = a - t * e;
        dist2 = min(dist2, dot(q, q));
        inside = inside && (e.x * a.y - e.y * a.x >= 0.0);
    }
    return dist2 <= r * r || (poly_ccw != 0 && inside);
}

// The node is kept by the CPU traversal: not wholly in padding, its disc meets the hull.
bool visible(ivec4 n) {
    int s = 1 << (k - n.y);
    ivec4 b1 = blk[4 * n.x + 1];
    if (n.z * s >= b1.z - 1 || n.w * s >= b1.w - 1) return false;
    return n_poly == 0 || meets_hull(centre_xy(n), half_diagonal(n.y));
}

float chunk_error(ivec4 n) {
    int d = n.y;
    if (d + chunk >= k) return 0.0;
    return eps[blk[4 * n.x + 1].x + ((1 << (2 * d)) - 1) / 3 + (n.z << d) + n.w];
}

// kim_metric: pixel distance of the sphere's point nearest the eye and that point raised by ε.
float screen_error(ivec4 n) {
    float e = chunk_error(n);
    if (e == 0.0) return 0.0;
    const float INF = uintBitsToFloat(0x7f800000u);
    vec2 z = vec2(intBitsToFloat(blk[4 * n.x + 3].x), intBitsToFloat(blk[4 * n.x + 3].y));
    vec3 c = vec3(centre_xy(n), 0.5 * (z.x + z.y) - cam_frac.z);
    float hd = half_diagonal(n.y), zh = 0.5 * (z.y - z.x);
    float r = sqrt(hd * hd + zh * zh);
    float dist = length(c);
    if (dist <= r || isinf(e)) return INF;
    vec3 p = c - c * (r / dist);
    vec4 a = mvp * vec4(p, 1.0), b = mvp * vec4(p + vec3(0.0, 0.0, e), 1.0);
    if (a.w <= 0.0 || b.w <= 0.0) return INF;
    float rho = length(viewport * (b.xy / b.w - a.xy / a.w));
    return isnan(rho) ? INF : rho;
}

// an infinite error (a mixed terrain/nodata node, the eye inside the sphere) always splits,
// whatever the float32 tau (gpu.py clamps it to float32's max: a huge tau is not inf here)
bool wants(ivec4 n) {
    float e = screen_error(n);
    return n.y < start_depth || isinf(e) || !(e <= tau);
}
bool refinable(ivec4 n) { return n.y + chunk < k; }
bool allowed(ivec4 n) { return n.y + chunk < blk[4 * n.x].w; }
bool splits(ivec4 n) { return refinable(n) && allowed(n) && wants(n); }
int level_of(ivec4 n) { return min(min(k, n.y + chunk), blk[4 * n.x].w); }

// The same-depth node across edge dir (N, E, S, W) of n; .x = -1 when there is none.
ivec4 beside(ivec4 n, int dir) {
    ivec2 st = dir == 0 ? ivec2(-1, 0) : dir == 1 ? ivec2(0, 1)
             : dir == 2 ? ivec2(1, 0) : ivec2(0, -1);
    int m = (1 << n.y) - 1, r = n.z + st.x, c = n.w + st.y, b = n.x;
    if (r < 0 || r > m || c < 0 || c > m) {
        b = blk[4 * n.x + 2][dir];
        r &= m;
        c &= m;
    }
    return ivec4(b, n.y, r, c);
}
