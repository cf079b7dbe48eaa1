"""OpenGL rendering of cubes onto output grids (the only package that touches OpenGL).

Modules: ``context`` (per-thread EGL context, shader loading), ``mesh`` (ground mesh of a cube),
``renderer`` (:func:`render_cube`), ``reference`` (slow numpy reference for tests). Importing this
package imports neither moderngl nor any module: import the one you need.
"""
