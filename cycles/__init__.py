"""Blender Cycles' skin models: the scene built in Blender from dermis's arrays, rendered in
a process of its own, and the mappings from dermis's layer stack to Cycles' inputs
(docs/cycles.md)."""
