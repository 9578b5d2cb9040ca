"""GLSL sources: heights fetched on the GPU (Qiu's steps 1-4), snapping, shading, wireframe."""

from __future__ import annotations

# Shared vertex logic. Per vertex: in_grid = (i, j) of a P x P patch mesh. Per instance:
# in_a = (block col0, block row0) global sample of the block origin, (node col0, node row0)
#        in block samples; in_b = (slot base in the height buffer, level, cells_log2, snaps
#        packed 4 bits each N | E<<4 | S<<8 | W<<12).
# Height fetch and vertex construction shared by every stage that makes terrain vertices (the
# vertex shader here, the tessellation evaluation shader of render/strategies/chunk_tess.py):
# vertex_at(a, b, si, sj) builds the vertex at (already snapped) patch cell (si, sj) of the
# instance (a, b) laid out as below.
FETCH_COMMON = """
#version 450
layout(std430, binding = 0) readonly buffer Heights { float heights[]; };
layout(binding = 1) uniform usampler2D level_tex;
layout(binding = 2) uniform isampler2D order_tex;
uniform int k;
uniform int patch_log2;
uniform ivec2 cam_cell;     // integer global sample (col, row) near the camera
uniform vec3 cam_frac;      // camera - that sample's world position (x, y), and camera z
uniform vec2 spacing;       // dx, dy
uniform mat4 mvp;           // projection * camera-relative view

const float MASKED = -1.0e30;

int level_start(int lv) {
    if (lv == 0) return 0;
    int s = (1 << (lv - 1)) + 1;
    return s * s;
}

float fetch(int base, ivec2 cr) {
    int lv = int(texelFetch(level_tex, cr, 0).r);      // step 2: level index
    int ord = texelFetch(order_tex, cr, 0).r;          // step 3: order index
    return heights[base + level_start(lv) + ord];      // step 4: start(level) + order
}

struct Vtx { vec3 rel; float h; float masked; vec3 normal; int level; ivec2 g; };

Vtx vertex_at(ivec4 a, ivec4 b, int si, int sj) {
    int base = b.x;
    int lv = b.y;
    int s = 1 << (k - lv);
    ivec2 cr = ivec2(a.z + si * s, a.w + sj * s);     // step 1: block sample (col, row)
    float h = fetch(base, cr);
    Vtx v;
    v.masked = h <= MASKED ? 1.0e6 : 0.0;
    if (h <= MASKED) h = 0.0;
    int side = (1 << k);
    ivec2 w = ivec2(max(cr.x - s, 0), cr.y), e = ivec2(min(cr.x + s, side), cr.y);
    ivec2 nn = ivec2(cr.x, max(cr.y - s, 0)), ss = ivec2(cr.x, min(cr.y + s, side));
    float hw = fetch(base, w), he = fetch(base, e), hn = fetch(base, nn), hs = fetch(base, ss);
    if (hw <= MASKED) hw = h;
    if (he <= MASKED) he = h;
    if (hn <= MASKED) hn = h;
    if (hs <= MASKED) hs = h;
    float dzdx = (he - hw) / (float(e.x - w.x) * spacing.x);
    float dzdy = (hn - hs) / (float(ss.y - nn.y) * spacing.y);
    v.normal = normalize(vec3(-dzdx, -dzdy, 1.0));
    ivec2 g = a.xy + cr;
    v.rel = vec3(float(g.x - cam_cell.x) * spacing.x - cam_frac.x,
                 -float(g.y - cam_cell.y) * spacing.y - cam_frac.y,
                 h - cam_frac.z);
    v.h = h;
    v.level = lv;
    v.g = g;
    return v;
}
"""

# Shared vertex logic. Per vertex: in_grid = (i, j) of a P x P patch mesh. Per instance:
# in_a = (block col0, block row0) global sample of the block origin, (node col0, node row0)
#        in block samples; in_b = (slot base in the height buffer, level, cells_log2, snaps
#        packed 4 bits each N | E<<4 | S<<8 | W<<12).
VERTEX_COMMON = (
    FETCH_COMMON
    + """
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
"""
)

EMIT = """
out vec3 v_normal;
out float v_h;
out float v_masked;
flat out int v_level;
void emit(Vtx v) {
    gl_Position = mvp * vec4(v.rel, 1.0);
    v_normal = v.normal;
    v_h = v.h;
    v_masked = v.masked;
    v_level = v.level;
}
"""
"""The varyings every strategy's last vertex stage hands to the shared fragment shader."""

VERTEX = VERTEX_COMMON + EMIT + "void main() { emit(make_vertex()); }\n"

# Transform feedback probe: the fetched height and global sample of every vertex.
PROBE = (
    VERTEX_COMMON
    + """
out float out_h;
out vec2 out_g;
void main() {
    Vtx v = make_vertex();
    out_h = v.masked > 0.0 ? -1.0e30 : v.h;
    out_g = vec2(v.g);
}
"""
)

SHADE = """
uniform vec3 sun;
uniform vec2 zrange;
uniform int lod_colour;
vec3 ramp(float h) {
    if (h < 0.0) {
        float t = clamp(-h / max(zrange.y, 1.0), 0.0, 1.0);
        return mix(vec3(0.25, 0.55, 0.85), vec3(0.05, 0.15, 0.45), sqrt(t));
    }
    float t = clamp((h - max(zrange.x, 0.0)) / max(zrange.y - max(zrange.x, 0.0), 1e-6), 0.0, 1.0);
    vec3 c0 = vec3(0.20, 0.45, 0.20), c1 = vec3(0.55, 0.65, 0.30), c2 = vec3(0.60, 0.45, 0.30);
    vec3 c3 = vec3(0.50, 0.45, 0.42), c4 = vec3(0.95, 0.95, 0.97);
    if (t < 0.25) return mix(c0, c1, t / 0.25);
    if (t < 0.55) return mix(c1, c2, (t - 0.25) / 0.30);
    if (t < 0.80) return mix(c2, c3, (t - 0.55) / 0.25);
    return mix(c3, c4, (t - 0.80) / 0.20);
}
vec3 level_colour(int lv) {
    float a = float(lv) * 0.618034;
    return 0.5 + 0.5 * cos(6.2831853 * (fract(a) + vec3(0.0, 0.33, 0.67)));
}
vec3 shade(vec3 n, float h, int lv) {
    vec3 base = ramp(h);
    if (lod_colour != 0) base = mix(base, level_colour(lv), 0.6);
    float lambert = max(dot(normalize(n), normalize(sun)), 0.0);
    return base * (0.35 + 0.65 * lambert);
}
"""

FRAGMENT = (
    """
#version 450
in vec3 v_normal;
in float v_h;
in float v_masked;
flat in int v_level;
out vec4 f_colour;
"""
    + SHADE
    + """
void main() {
    if (v_masked > 0.0) discard;
    f_colour = vec4(shade(v_normal, v_h, v_level), 1.0);
}
"""
)

# Wireframe overlay: a geometry shader passes edge distances (in pixels) to the fragments.
GEOMETRY = """
#version 450
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
uniform vec2 viewport;
in vec3 v_normal[];
in float v_h[];
in float v_masked[];
flat in int v_level[];
out vec3 g_normal;
out float g_h;
out float g_masked;
flat out int g_level;
noperspective out vec3 g_dist;
void main() {
    vec2 p[3];
    for (int i = 0; i < 3; i++) p[i] = viewport * gl_in[i].gl_Position.xy / gl_in[i].gl_Position.w;
    vec2 e1 = p[1] - p[0], e2 = p[2] - p[0];
    float area = abs(e1.x * e2.y - e1.y * e2.x);
    if (area == 0.0) return;
    vec3 d = vec3(area / length(p[2] - p[1]), area / length(p[2] - p[0]),
                  area / length(p[1] - p[0]));
    for (int i = 0; i < 3; i++) {
        gl_Position = gl_in[i].gl_Position;
        g_normal = v_normal[i]; g_h = v_h[i]; g_masked = v_masked[i]; g_level = v_level[i];
        g_dist = vec3(0.0); g_dist[i] = d[i];
        EmitVertex();
    }
    EndPrimitive();
}
"""

FRAGMENT_WIRE = (
    """
#version 450
in vec3 g_normal;
in float g_h;
in float g_masked;
flat in int g_level;
noperspective in vec3 g_dist;
out vec4 f_colour;
"""
    + SHADE
    + """
void main() {
    if (g_masked > 0.0) discard;
    vec3 c = shade(g_normal, g_h, g_level);
    float d = min(g_dist.x, min(g_dist.y, g_dist.z));
    float edge = 1.0 - smoothstep(0.0, 1.0, d);
    f_colour = vec4(mix(c, vec3(0.05), edge * 0.8), 1.0);
}
"""
)

# Triangle read-back: a geometry shader after any vertex stage that outputs ``t_gh`` = (global
# col, global row, height or -1e30 where masked) appends each triangle's 3 corners to the SSBO
# at binding 3 (a uint count, 3 pad words, then 9 floats per triangle), up to ``cap``; run with
# the rasteriser discarded. See render.strategies.base.read_triangles.
TRIANGLE_PROBE = """
#version 450
layout(triangles) in;
layout(points, max_vertices = 1) out;
layout(std430, binding = 3) buffer Tris {
    uint count; uint pad0; uint pad1; uint pad2; float data[];
};
uniform uint cap;
in vec3 t_gh[];
void main() {
    uint i = atomicAdd(count, 1u);
    if (i < cap) {
        for (int j = 0; j < 3; j++) {
            data[9u * i + uint(3 * j)] = t_gh[j].x;
            data[9u * i + uint(3 * j + 1)] = t_gh[j].y;
            data[9u * i + uint(3 * j + 2)] = t_gh[j].z;
        }
    }
}
"""
