// The tessellated chunk vertex: tess_vertex().
#include "fetch.glsl"
layout(quads, equal_spacing, ccw) in;
patch in ivec4 p_a;
patch in ivec4 p_b;
Vtx tess_vertex() {
    float n = float(1 << p_b.z);
    int si = int(round(gl_TessCoord.x * n));
    int sj = int(round(gl_TessCoord.y * n));
    return vertex_at(p_a, p_b, si, sj);
}
