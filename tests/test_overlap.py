"""The overlap rules as objects (issue 31, :mod:`archive.overlap`): resolved once from a name with a
one-line error, passed whole (small pickles, stable Dask tokens), listed once (the CLI's choices, the
viewer's list), and each rule's chunk writer writing what its strategy object assembles."""

from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest

from archive.errors import InputError
from archive.overlap import LAST, MEAN, NADIR, RULES, overlap_rule
from helpers import FOV


def test_names_resolve_once_to_the_singletons():
    assert [overlap_rule(name) for name in ("last", "nadir", "mean")] == [LAST, NADIR, MEAN]
    assert overlap_rule(NADIR) is NADIR
    with pytest.raises(InputError) as info:
        overlap_rule("first")
    assert str(info.value).count("\n") == 0
    assert "--overlap" in str(info.value) and "'first'" in str(info.value) and "last, nadir, mean" in str(info.value)
    # what each rule needs and gives
    assert (LAST.key, NADIR.key, MEAN.key) == (None, "view_zenith", None)
    assert (LAST.single_source, NADIR.single_source, MEAN.single_source) == (True, True, False)


def test_rules_pickle_by_reference_and_tokenize_by_name():
    """A rule travels in every assemble task of a Dask graph: a few bytes, the same object back, and
    the same token in another process (graph keys are stable between runs)."""
    from dask.base import tokenize

    for rule in RULES.values():
        data = pickle.dumps(rule)
        assert len(data) < 64 and pickle.loads(data) is rule
    tokens = [tokenize(rule) for rule in RULES.values()]
    assert len(set(tokens)) == 3
    code = ("from dask.base import tokenize; from archive.overlap import RULES; "
            "print(' '.join(tokenize(r) for r in RULES.values()))")
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert other.stdout.split() == tokens


def test_options_hold_the_rule_and_records_keep_the_name(tmp_path):
    """RenderOptions holds the object; its JSON record (an Item's recipe) and its command line name it."""
    from archive.run.batch import recipe_request
    from archive.catalog.product import render_command
    from archive.run.options import RenderOptions

    options = RenderOptions.create(["flight"], gsd=0.5, fov=FOV, overlap="nadir")
    assert options.overlap is NADIR and RenderOptions.create(["flight"], gsd=0.5).overlap is LAST
    assert recipe_request(options)["overlap"] == "nadir"
    assert "--overlap nadir" in render_command(options, "out.zarr")
    with pytest.raises(InputError, match="--overlap: unknown overlap rule 'first'"):
        RenderOptions.create(["flight"], gsd=0.5, overlap="first")
    refused = RenderOptions.create([tmp_path], gsd=0.5, fov=FOV, overlap="mean", provenance=True)
    with pytest.raises(InputError, match="--overlap last or nadir with --provenance"):
        refused.check()


def test_the_lists_come_from_the_registry(capsys):
    """The CLI's --overlap choices and the viewer's list (single-source rules only) are the registry's."""
    from archive.cli import build_parser
    from archive.drawing.query import OVERLAPS

    parser = build_parser()
    for name in RULES:
        assert parser.parse_args(["render", "flight", "--gsd", "1", "--out", "x.zarr", "--overlap", name]).overlap == name
    with pytest.raises(SystemExit):
        parser.parse_args(["render", "flight", "--gsd", "1", "--out", "x.zarr", "--overlap", "first"])
    err = capsys.readouterr().err
    assert "invalid choice: 'first'" in err and all(name in err.rpartition("choose from")[2] for name in RULES)
    assert [c.as_dict() for c in OVERLAPS] == [r.as_dict() for r in RULES.values() if r.single_source]


class _Writer:
    """A sink's tile writer as the rules see it: one reusable buffer larger than the tile (the grid's
    outside part), each written band copied out."""

    def __init__(self, shape):
        self.array = np.full(shape, 7.0, np.float32)   # not NaN: the outside part must be written NaN
        self.bands = {}

    def buffer(self):
        return self.array

    def write(self, band, buffer):
        self.bands[band] = buffer.copy()


@pytest.mark.parametrize("rule", list(RULES.values()), ids=list(RULES))
def test_each_rules_chunk_writer_writes_what_it_assembles(rule):
    """Per rule, :meth:`write_bands` (band by band into a reusable buffer: the 'last' and 'nadir' fast
    paths) writes bit for bit the tile :meth:`assemble` builds, NaN outside the tile, and the same
    saturation mask; :meth:`shown` names the capture whose values a pixel shows."""
    rng = np.random.default_rng(7)
    nbands, height, width = 3, 9, 8
    boxes = [(slice(0, 6), slice(0, 5)), (slice(2, 8), slice(1, 7)), (slice(1, 5), slice(3, 7))]
    parts, keys = [], []
    for rows, cols in boxes:
        h, w = rows.stop - rows.start, cols.stop - cols.start
        values = rng.normal(size=(nbands, h, w)).astype(np.float32)
        values[:, 0, 0] = np.nan
        values[1, -1, -1] = np.nan          # one band missing: 'last' takes the band from an earlier part
        parts.append((values, rng.random((h, w)) < 0.3, rows, cols))
        key = rng.choice([1.0, 2.0, 3.0], size=(h, w)).astype(np.float32)
        key[0, 0] = np.nan
        keys.append(key)
    keys = keys if rule.key is not None else None
    values, saturated = rule.assemble(nbands, height, width, parts, keys)
    writer = _Writer((height + 2, width + 3))
    written_sat = rule.write_bands(writer, nbands, height, width, parts, keys, saturation=True)
    assert sorted(writer.bands) == list(range(nbands))
    for b in range(nbands):
        band = writer.bands[b]
        assert np.array_equal(band[:height, :width], values[b], equal_nan=True), (rule.name, b)
        assert np.isnan(band[height:]).all() and np.isnan(band[:height, width:]).all()
    assert np.array_equal(written_sat, saturated)
    assert rule.write_bands(_Writer((height, width)), nbands, height, width, parts, keys, saturation=False) is None
    # the capture one pixel shows: (4, 4) is covered by all three parts
    at = [(values_[:, 4 - r.start, 4 - c.start], None if keys is None else float(keys[i][4 - r.start, 4 - c.start]))
          for i, (values_, _, r, c) in enumerate(parts)]
    shown = rule.shown([k for _, k in at])
    if rule.single_source:
        assert np.array_equal(at[shown][0][np.isfinite(at[shown][0])], values[:, 4, 4][np.isfinite(at[shown][0])])
    if rule is NADIR:
        finite = [(k, i) for i, (_, k) in enumerate(at) if np.isfinite(k)]
        assert shown == max(finite, key=lambda ki: (-ki[0], ki[1]))[1]   # lowest key, the later on a tie
    else:
        assert shown == len(parts) - 1
