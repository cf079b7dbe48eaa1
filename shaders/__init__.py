"""GLSL shaders of the renderer, loaded by name (see archive.render.context)."""
