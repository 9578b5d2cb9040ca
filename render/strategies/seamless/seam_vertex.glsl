// A seamless-patch vertex from the cached meshes: seam_vertex().
#include "fetch.glsl"
layout(std430, binding = 4) readonly buffer Inst { ivec4 inst[]; };
uniform int inst0;
uniform int res_log2;
in ivec3 in_uvr;
Vtx seam_vertex() {
    int id = inst0 + gl_InstanceID;
    ivec4 a = inst[2 * id];
    ivec4 b = inst[2 * id + 1];
    int n = 1 << res_log2;
    int u = in_uvr.x, v = in_uvr.y;
    for (int i = 0; i < b.z; i++) { int t = u; u = n - v; v = t; }
    int sh = res_log2 - in_uvr.z;
    return vertex_at(a, ivec4(b.x, b.y - sh, 0, 0), u >> sh, v >> sh);
}
