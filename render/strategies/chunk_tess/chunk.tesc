#version 450
layout(vertices = 1) out;
flat in ivec4 c_a[];
flat in ivec4 c_b[];
patch out ivec4 p_a;
patch out ivec4 p_b;
void main() {
    p_a = c_a[0];
    p_b = c_b[0];
    int c = c_b[0].z, w = c_b[0].w;
    int tn = w & 15, te = (w >> 4) & 15, ts = (w >> 8) & 15, tw = (w >> 12) & 15;
    float n = float(1 << c);
    gl_TessLevelInner[0] = n;
    gl_TessLevelInner[1] = n;
    gl_TessLevelOuter[0] = float(1 << (c - tw));   // u = 0: west
    gl_TessLevelOuter[1] = float(1 << (c - tn));   // v = 0: north
    gl_TessLevelOuter[2] = float(1 << (c - te));   // u = 1: east
    gl_TessLevelOuter[3] = float(1 << (c - ts));   // v = 1: south
}
