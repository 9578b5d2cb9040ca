#version 450
in ivec4 in_a;
in ivec4 in_b;
flat out ivec4 v_a;
flat out ivec4 v_b;
void main() { v_a = in_a; v_b = in_b; }
