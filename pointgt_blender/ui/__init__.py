"""Blender classes the user sees: per-object properties, add-on preferences, the 3D View and Image Editor panels."""
