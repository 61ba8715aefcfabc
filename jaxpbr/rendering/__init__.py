"""Rendering scenes: geometry, visibility, texture filtering, the staged renderer."""
