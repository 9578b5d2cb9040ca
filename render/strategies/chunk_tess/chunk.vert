#version 450
in ivec4 in_a;
in ivec4 in_b;
flat out ivec4 c_a;
flat out ivec4 c_b;
void main() { c_a = in_a; c_b = in_b; }
