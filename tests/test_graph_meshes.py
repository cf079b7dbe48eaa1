"""Cube meshes are built by tasks on the workers, not shipped in the graph (issue 19, DESIGN 9).

A terrain flight's meshes are MBs (a 3-cube --dem render sent a 6-10 MiB graph); the graph now
carries one small mesh task per cube (the source, the cube index and the plan's
:class:`~archive.params.MeshSpec`), whose mesh is the one the client planned the cube's window
with. Flights come from test_terrain.py's session cache (simulated once).
"""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from helpers import FOV

GSD = 0.05
#: Largest pickled value or task a render graph may hold besides its sources (KiB).
SMALL_KIB = 32


def _build(directory, tmp_path, **options):
    from archive.run.options import RenderOptions
    from archive.outputs.publish import Output
    from archive.run.pipeline import build_output, open_inputs, plan_output

    request = RenderOptions(sources=(str(directory),), gsd=GSD, fov=FOV, **options)
    inputs = open_inputs(request, request.check(), mosaic=True)
    planned = plan_output(inputs)
    output = Output(tmp_path / "out.zarr")
    sink, graph = build_output(planned, output)
    return inputs, planned, output, graph


def _graph_items(graph) -> dict:
    from dask.highlevelgraph import HighLevelGraph

    return dict(HighLevelGraph.merge(*[d.dask for d in graph.writes]))


def _same_mesh(a, b) -> bool:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or not np.array_equal(x, y, equal_nan=True):
                return False
        elif f.name == "ground_height":
            if not (x == y or (np.isnan(x) and np.isnan(y))):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("terrain", [True, False])
def test_graph_carries_mesh_tasks_not_meshes(hills, tmp_path, terrain):
    from archive.graph.plan import cube_meshes, mesh_task
    from archive.render.mesh import Mesh

    directory, truth = hills
    options = {"dem": str(directory / "dem.tif")} if terrain else {"ground_height": str(truth.ground_height)}
    inputs, planned, output, graph = _build(directory, tmp_path, **options)
    try:
        items = _graph_items(graph)
        meshes = {k: v for k, v in items.items() if str(k).startswith("mesh-")}
        assert len(meshes) == len(planned.plan.jobs) >= 2
        assert all(v.func is mesh_task for v in meshes.values())
        assert all(job.mesh is None for job in planned.plan.jobs)   # the client keeps windows only
        big = {}
        for key, value in items.items():
            size = len(pickle.dumps(value)) / 1024
            if not str(key).startswith("source-") and size > SMALL_KIB:
                big[key] = size
            assert not isinstance(getattr(value, "value", value), Mesh), key
        assert not big, f"values over {SMALL_KIB} KiB in the graph: {big}"
        if terrain:   # what the bound keeps out: the client's terrain meshes are larger
            client = inputs.meshes[0]
            assert max(len(pickle.dumps(m)) for m in client) / 1024 > SMALL_KIB
        # each task's mesh is the one the plan's window came from (same arrays, same CRS)
        source = planned.sources[0]
        params = planned.plan.mesh_spec
        assert params == planned.mesh_spec and params.epsg == planned.plan.grid.epsg
        flight = (list(inputs.meshes[0]) if terrain else
                  cube_meshes(source, FOV, float(truth.ground_height), planned.mesh_spec.max_view_angle))
        for j, job in enumerate(planned.plan.jobs):
            mesh = mesh_task(source, job.cube, params)
            assert mesh.epsg == planned.plan.grid.epsg
            assert _same_mesh(mesh, flight[job.cube]), job.cube
    finally:
        output.cleanup()


def test_lazy_mosaic_builds_meshes_in_tasks_too(hills):
    import archive

    directory, truth = hills
    ds = archive.mosaic([str(directory)], gsd=GSD, fov=FOV, dem=str(directory / "dem.tif"))
    graph = dict(ds["radiance"].data.__dask_graph__())
    meshes = [k for k in graph if str(k).startswith("mesh-")]
    assert meshes and all(type(graph[k]).__name__ != "DataNode" for k in meshes)
