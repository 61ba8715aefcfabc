"""Geometry: pure array math on vertices and transforms, for NumPy and JAX alike: glTF animation
sampling (`animation`) and posing (`pose`: node hierarchies, morph targets, skinning)."""
