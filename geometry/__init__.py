"""Surfaces of the head: scan readers, the procedural head, repair, subdivision, simplification,
UV transfer, baking texture-space maps and bump frames, face regions."""
