// Height fetch from the pool and vertex construction (see render/shaders.py).
layout(std430, binding = 0) readonly buffer Heights { float heights[]; };
layout(binding = 1) uniform usampler2D level_tex;
layout(binding = 2) uniform isampler2D order_tex;
uniform int k;
uniform int patch_log2;
uniform ivec2 cam_cell;     // integer global sample (col, row) near the camera
uniform vec3 cam_frac;      // camera - that sample's world position (x, y), and camera z
uniform float cam_z;        // camera z - the store's reference height (heights are relative)
uniform vec2 spacing;       // dx, dy
uniform mat4 mvp;           // projection * camera-relative view

const float MASKED = MASKED_HEIGHT;

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
                 h - cam_z);
    v.h = h;
    v.level = lv;
    v.g = g;
    return v;
}
