#version 450
in ivec4 in_a;
flat out ivec4 v_a;
void main() { v_a = in_a; }
