"""Dask graph construction for ``archive render`` (builds graphs, never computes them).

- :mod:`archive.graph.plan`: metadata only: cube meshes, strips, output grid, cube windows.
- :mod:`archive.graph.build`: the render -> assemble -> write graph with deterministic keys.
- :mod:`archive.graph.tasks`: the task bodies, plain functions callable without Dask.
"""
