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
