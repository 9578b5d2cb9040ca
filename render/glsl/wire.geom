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
        gl_ClipDistance[0] = gl_in[i].gl_ClipDistance[0];  // (emit.glsl's nodata clip)
        g_normal = v_normal[i]; g_h = v_h[i]; g_masked = v_masked[i]; g_level = v_level[i];
        g_dist = vec3(0.0); g_dist[i] = d[i];
        EmitVertex();
    }
    EndPrimitive();
}
