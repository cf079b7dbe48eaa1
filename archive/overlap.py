"""Overlap rules: what an output pixel shows where several captures (cubes, flights) cover it.

A rule is resolved once from its name (``archive render --overlap``, ``overlap=`` of the API and the
viewer) by :func:`overlap_rule` into one of the module's singletons, :data:`LAST`, :data:`NADIR` and
:data:`MEAN`, and handed on whole: :class:`~archive.run.options.RenderOptions` holds it, the graph
builders, the task bodies and the viewer ask it, and nobody tests its name again (rio-tiler's
``MosaicMethodBase`` instances; STYLE 16 and 18). A rule owns:

- its ``name`` and ``label`` (the CLI's choices and the viewer's list, :data:`RULES`);
- what it needs: ``needs``, the provenance layer it compares (:mod:`archive.geometry.provenance`;
  ``view_zenith`` for 'nadir'), and ``key``, that layer or None;
- what it gives: ``wins`` ('last': the latest capture; 'lowest': the one with the lowest key; None:
  the pixel mixes captures), hence ``single_source`` (whether provenance layers can be written);
- how it combines renders: :meth:`OverlapRule.mosaic`, a fresh per-tile strategy object (``feed``
  the renders in capture order, then ``result()``), and :meth:`OverlapRule.write_bands`, its chunk
  writer's path (band by band into the sink's reusable buffer; 'last' and 'nadir' never build the
  tile), and :meth:`OverlapRule.shown`, the capture one pixel shows (the viewer's point spectrum).

Rules: 'last' (the later capture wins), 'nadir' (the capture seen closest to nadir wins, the later
one on a tie: NEON's mosaics), 'mean' (mean of the covering captures).

Arrays are ``(band, y, x)`` float32 with NaN where a capture does not cover a pixel; ``saturated``
is ``(y, x)`` bool (some band of the group was saturated there); ``key`` is ``(y, x)`` float32, the
compared layer of the capture's line at each pixel (view zenith, degrees; NaN where not covered),
fed only to rules that declare they need it. A *part* is ``(values, saturated, rows, cols)``: a
render landing at ``[..., rows, cols]`` of the tile.

The rules pickle by reference (their module-level name: a few bytes in a Dask graph) and tokenize
by name. numpy is imported inside the functions, so that ``archive --help`` (which lists the
names) stays light.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

from archive.errors import InputError

if TYPE_CHECKING:
    import numpy as np

__all__ = ["LAST", "MEAN", "NADIR", "RULES", "LastRule", "MeanRule", "NadirRule", "OverlapRule", "TileMosaic",
           "last_saturation", "last_values", "nadir_values", "nadir_winners", "overlap_rule"]

Part = tuple["np.ndarray", "np.ndarray", slice, slice]


# ---------------------------------------------------------------------------------------------
# The rules' arithmetic (shared by the strategy objects and the chunk writers)
# ---------------------------------------------------------------------------------------------
def last_values(out: np.ndarray, parts: Sequence[tuple[np.ndarray, slice, slice]]) -> np.ndarray:
    """The 'last' rule's values, written into ``out`` (..., H, W) float32 and returned: per value, the
    latest finite value of the ``parts`` covering it, NaN where none is finite.

    parts: (values (..., h, w), rows, cols) in capture order, ``values`` landing at
    ``out[..., rows, cols]``. The first part is copied straight in (NaN only around it, non-finite
    values turned to NaN): one pass instead of a fill and a masked copy.
    """
    import numpy as np

    if not parts:
        out[...] = np.nan
        return out
    first, rows, cols = parts[0]
    out[..., :rows.start, :] = np.nan
    out[..., rows.stop:, :] = np.nan
    out[..., rows, :cols.start] = np.nan
    out[..., rows, cols.stop:] = np.nan
    target = out[..., rows, cols]
    np.copyto(target, first)
    infinite = np.isinf(target)
    if infinite.any():
        target[infinite] = np.nan
    for values, rows, cols in parts[1:]:
        np.copyto(out[..., rows, cols], values, where=np.isfinite(values))
    return out


def last_saturation(height: int, width: int, parts: Sequence[Part]) -> np.ndarray:
    """The 'last' rule's saturation mask (height, width) bool: the flag of the last part covering
    the pixel (some band finite there), False where none does.

    parts: (values (band, h, w), saturated (h, w), rows, cols) in capture order. Evaluated only
    where some part is flagged (saturation is rare).
    """
    import numpy as np

    flagged = np.zeros((height, width), bool)
    for _, part_sat, rows, cols in parts:
        flagged[rows, cols] |= part_sat
    ys, xs = np.nonzero(flagged)
    saturated = np.zeros((height, width), bool)
    if not ys.size:
        return saturated
    result = np.zeros(ys.size, bool)
    for values, part_sat, rows, cols in parts:
        inside = np.flatnonzero((ys >= rows.start) & (ys < rows.stop) & (xs >= cols.start) & (xs < cols.stop))
        r, c = ys[inside] - rows.start, xs[inside] - cols.start
        covered = np.isfinite(values[:, r, c]).any(axis=0)
        result[inside[covered]] = part_sat[r[covered], c[covered]]
    saturated[ys, xs] = result
    return saturated


def nadir_winners(height: int, width: int, keys: Sequence[tuple[np.ndarray, slice, slice]]) -> np.ndarray:
    """The 'nadir' rule's choice: (height, width) int32, per pixel the index of the part with the
    smallest key (view zenith), the later one on a tie, -1 where no key is finite.

    keys: (key (h, w) float32, NaN where the part does not cover the pixel; rows, cols) in capture
    order, ``key`` landing at ``[rows, cols]``.
    """
    import numpy as np

    best = np.full((height, width), np.inf, np.float32)
    winner = np.full((height, width), -1, np.int32)
    for k, (key, rows, cols) in enumerate(keys):
        wins = key <= best[rows, cols]         # NaN (not covered) never wins
        best[rows, cols][wins] = key[wins]
        winner[rows, cols][wins] = k
    return winner


def nadir_values(out: np.ndarray, winner: np.ndarray, parts: Sequence[tuple[np.ndarray, slice, slice]],
                 fill=float("nan")) -> np.ndarray:
    """The 'nadir' rule's values, written into ``out`` (..., H, W) and returned: each pixel's value
    from the part :func:`nadir_winners` chose (``winner``), ``fill`` where none.

    parts: (values (..., h, w), rows, cols) in the order of the winners' keys.
    """
    import numpy as np

    out[...] = fill
    for k, (values, rows, cols) in enumerate(parts):
        np.copyto(out[..., rows, cols], values, where=winner[rows, cols] == k)
    return out


def _bounded(s: slice, size: int) -> slice:
    """``s`` with explicit start and stop within 0..size (step 1)."""
    start, stop, step = s.indices(size)
    if step != 1:
        raise ValueError(f"mosaic parts need contiguous slices, got step {step}")
    return slice(start, max(start, stop))


# ---------------------------------------------------------------------------------------------
# Per-tile strategy objects: feed renders in capture order, then take result()
# ---------------------------------------------------------------------------------------------
class TileMosaic:
    """One tile's mosaic under a rule: :meth:`feed` it the renders in capture order, then take
    :meth:`result` (values (nbands, height, width) float32, saturated (height, width) bool) and, for
    a rule that compares a key, :meth:`winning_key`."""

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice,
             key: np.ndarray | None = None) -> None:
        raise NotImplementedError

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def winning_key(self) -> np.ndarray | None:
        """(height, width) float32: the key of the capture each pixel shows (NaN where none), after
        :meth:`result`; None for a rule that compares no key."""
        return None


class _LastTile(TileMosaic):
    """The later capture wins wherever it covers the pixel (per band: the later finite value wins).
    Renders are only collected by ``feed``; ``result`` combines them with :func:`last_values` and
    :func:`last_saturation`."""

    def __init__(self, nbands: int, height: int, width: int):
        self.shape = (nbands, height, width)
        self.parts: list[Part] = []

    def feed(self, values, saturated, rows, cols, key=None) -> None:
        self.parts.append((values, saturated, _bounded(rows, self.shape[1]), _bounded(cols, self.shape[2])))

    def result(self):
        import numpy as np

        values = last_values(np.empty(self.shape, np.float32), [(v, r, c) for v, _, r, c in self.parts])
        return values, last_saturation(self.shape[1], self.shape[2], self.parts)


class _MeanTile(TileMosaic):
    """Mean of the covering captures, leaving saturated samples out (unless all are saturated); the
    saturation flag is the OR over every capture covering the pixel."""

    def __init__(self, nbands: int, height: int, width: int):
        import numpy as np

        shape = (nbands, height, width)
        self.total = np.zeros(shape, np.float64)
        self.count = np.zeros(shape, np.uint16)
        self.total_sat = np.zeros(shape, np.float64)   # saturated samples: used only if nothing else
        self.count_sat = np.zeros(shape, np.uint16)
        self.saturated = np.zeros((height, width), bool)

    def feed(self, values, saturated, rows, cols, key=None) -> None:
        import numpy as np

        ok = np.isfinite(values)
        good = ok & ~saturated[None]
        bad = ok & saturated[None]
        v = np.where(ok, values, 0.0)
        self.total[:, rows, cols] += np.where(good, v, 0.0)
        self.count[:, rows, cols] += good
        self.total_sat[:, rows, cols] += np.where(bad, v, 0.0)
        self.count_sat[:, rows, cols] += bad
        self.saturated[rows, cols] |= saturated & ok.any(axis=0)

    def result(self):
        import numpy as np

        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(self.count > 0, self.total / self.count,
                            np.where(self.count_sat > 0, self.total_sat / self.count_sat, np.nan))
        return mean.astype(np.float32), self.saturated


class _NadirTile(TileMosaic):
    """The capture with the smallest key (view zenith) at the pixel wins (all its bands and its
    saturation flag), the later one on a tie; pixels no capture covers (key NaN) stay NaN. Renders
    are only collected by ``feed``; ``result`` picks with :func:`nadir_winners` and :func:`nadir_values`."""

    def __init__(self, nbands: int, height: int, width: int):
        self.shape = (nbands, height, width)
        self.parts: list[tuple[np.ndarray, np.ndarray, slice, slice, np.ndarray]] = []
        self.winner: np.ndarray | None = None

    def feed(self, values, saturated, rows, cols, key=None) -> None:
        if key is None:
            raise ValueError(f"the '{NADIR.name}' rule needs each render's {NADIR.key} (key)")
        rows, cols = _bounded(rows, self.shape[1]), _bounded(cols, self.shape[2])
        self.parts.append((values, saturated, rows, cols, key))

    def result(self):
        import numpy as np

        self.winner = nadir_winners(self.shape[1], self.shape[2], [(k, r, c) for _, _, r, c, k in self.parts])
        values = nadir_values(np.empty(self.shape, np.float32), self.winner,
                              [(v, r, c) for v, _, r, c, _ in self.parts])
        saturated = np.zeros(self.shape[1:], bool)
        nadir_values(saturated, self.winner, [(s, r, c) for _, s, r, c, _ in self.parts], fill=False)
        return values, saturated

    def winning_key(self):
        import numpy as np

        if self.winner is None:
            raise ValueError("winning_key() comes after result()")
        return nadir_values(np.empty(self.shape[1:], np.float32), self.winner, [(k, r, c) for _, _, r, c, k in self.parts])


# ---------------------------------------------------------------------------------------------
# The rules
# ---------------------------------------------------------------------------------------------
class OverlapRule:
    """An overlap rule (one instance per rule, the module's singletons; see the module docstring).

    name: ``--overlap``'s word; label: words for the viewer's list; needs: the provenance layers it
    compares (at most one, its :attr:`key`); wins: 'last' | 'lowest' | None (mixes captures).
    """

    name: ClassVar[str]
    label: ClassVar[str]
    needs: ClassVar[tuple[str, ...]] = ()
    wins: ClassVar[str | None] = None
    _tile: ClassVar[type[TileMosaic]]
    _global: ClassVar[str]   # the module-level name it pickles as

    @property
    def key(self) -> str | None:
        """The provenance layer the rule compares (fed to it as each render's ``key``), or None."""
        return self.needs[0] if self.needs else None

    @property
    def single_source(self) -> bool:
        """Whether each output pixel comes from one raw pixel (then provenance layers can be written)."""
        return self.wins is not None

    def mosaic(self, nbands: int, height: int, width: int) -> TileMosaic:
        """A fresh :class:`TileMosaic` for a tile of ``nbands`` x ``height`` x ``width``."""
        return self._tile(nbands, height, width)

    def assemble(self, nbands: int, height: int, width: int, parts: Sequence[Part],
                 keys: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The tile (values (nbands, height, width) float32, saturated (height, width) bool) of the
        ``parts`` in capture order, ``keys[i]`` the key of ``parts[i]`` (rules that compare one)."""
        mosaic = self.mosaic(nbands, height, width)
        for i, (values, saturated, rows, cols) in enumerate(parts):
            mosaic.feed(values, saturated, rows, cols, key=None if keys is None else keys[i])
        return mosaic.result()

    def write_bands(self, writer, nbands: int, height: int, width: int, parts: Sequence[Part],
                    keys: Sequence[np.ndarray] | None, saturation: bool) -> np.ndarray | None:
        """Mosaic ``parts`` (capture order, ``keys`` as for :meth:`assemble`) onto a tile of
        ``height`` x ``width`` and write it band by band through ``writer`` (a sink's open tile
        writer: ``buffer()``, before each band, a reusable (tile rows, tile cols) float32 buffer, at
        least the tile's size, whose outside part the rule sets NaN; ``write(band, buffer)``, which
        may go on reading it until a later ``buffer()`` returns it again). Returns the tile's saturation
        mask (height, width) bool when ``saturation``, else None.

        This one assembles the whole tile first (:meth:`assemble`); 'last' and 'nadir' write each
        band straight from the renders.
        """
        import numpy as np

        values, saturated = self.assemble(nbands, height, width, parts, keys)
        for b in range(nbands):
            buffer = writer.buffer()
            buffer[:height, :width] = values[b]
            buffer[height:] = np.nan  # the grid's outside part (zarr's padding of edge chunks)
            buffer[:height, width:] = np.nan
            writer.write(b, buffer)
        return saturated if saturation else None

    def shown(self, keys: Sequence[float | None]) -> int | None:
        """The index of the capture one pixel shows, of those covering it in capture order
        (``keys``: each one's key there, None for rules without one): the latest; None for none."""
        return len(keys) - 1 if len(keys) else None

    def as_dict(self) -> dict:
        """What the viewer's page needs of the rule: name, label, key plane, who wins."""
        return {"name": self.name, "label": self.label, "key": self.key, "wins": self.wins}

    def __reduce__(self) -> str:
        return self._global   # pickled by reference: the module-level singleton

    def __dask_tokenize__(self):
        return ("archive.overlap", self.name)

    def __str__(self) -> str:
        return self.name

    def __repr__(self) -> str:
        return f"<overlap rule {self.name!r}>"


def _check_buffer(tile_shape: tuple[int, int], buffer) -> None:
    if tile_shape[0] > buffer.shape[0] or tile_shape[1] > buffer.shape[1]:
        raise ValueError(f"tile {tile_shape} is larger than the sink's {buffer.shape} tile buffer")


class LastRule(OverlapRule):
    """'last': the later capture wins wherever it covers the pixel (per band: the later finite value)."""

    name = "last"
    label = "last on top"
    wins = "last"
    _tile = _LastTile
    _global = "LAST"

    def write_bands(self, writer, nbands, height, width, parts, keys, saturation):
        """Each band mosaicked by :func:`last_values` straight into the writer's buffer (the
        outside part left NaN) and written from there: no tile is built."""
        for b in range(nbands):
            buffer = writer.buffer()
            _check_buffer((height, width), buffer)
            last_values(buffer, [(values[b], rows, cols) for values, _, rows, cols in parts])
            writer.write(b, buffer)
        return last_saturation(height, width, parts) if saturation else None


class NadirRule(OverlapRule):
    """'nadir': the capture seen closest to nadir (lowest view zenith) wins, the later on a tie."""

    name = "nadir"
    label = "closest to nadir"
    needs = ("view_zenith",)
    wins = "lowest"
    _tile = _NadirTile
    _global = "NADIR"

    def write_bands(self, writer, nbands, height, width, parts, keys, saturation):
        """The winners chosen once (:func:`nadir_winners`), then each band written straight from the
        renders (:func:`nadir_values`): no tile is built."""
        import numpy as np

        if keys is None or len(keys) != len(parts):
            raise ValueError(f"the '{self.name}' rule needs the {self.key} of each of the {len(parts)} renders, "
                             f"got {None if keys is None else len(keys)}")
        winner = nadir_winners(height, width, [(k, rows, cols) for k, (_, _, rows, cols) in zip(keys, parts)])
        for b in range(nbands):
            buffer = writer.buffer()
            buffer[height:] = np.nan   # the grid's outside part (zarr's padding of edge chunks)
            buffer[:height, width:] = np.nan
            nadir_values(buffer[:height, :width], winner, [(values[b], rows, cols) for values, _, rows, cols in parts])
            writer.write(b, buffer)
        if not saturation:
            return None
        return nadir_values(np.empty((height, width), bool), winner, [(s, rows, cols) for _, s, rows, cols in parts],
                            fill=False)

    def shown(self, keys):
        """The capture with the lowest key (the later one on a tie), None where no key is finite."""
        import numpy as np

        if any(k is None for k in keys):
            raise ValueError(f"the '{self.name}' rule needs each capture's {self.key}")
        whole = slice(0, 1)
        winner = int(nadir_winners(1, 1, [(np.full((1, 1), k, np.float32), whole, whole) for k in keys])[0, 0])
        return None if winner < 0 else winner


class MeanRule(OverlapRule):
    """'mean': the mean of the covering captures (saturated samples left out unless all are)."""

    name = "mean"
    label = "mean of the captures"
    _tile = _MeanTile
    _global = "MEAN"


LAST = LastRule()
NADIR = NadirRule()
MEAN = MeanRule()
#: Every rule by name, the default first.
RULES: dict[str, OverlapRule] = {rule.name: rule for rule in (LAST, NADIR, MEAN)}


def overlap_rule(value: str | OverlapRule, option: str = "--overlap") -> OverlapRule:
    """The rule ``value`` names (a rule passes through); InputError naming ``option`` for an unknown
    name."""
    if isinstance(value, OverlapRule):
        return value
    rule = RULES.get(value) if isinstance(value, str) else None
    if rule is None:
        raise InputError(option, f"unknown overlap rule {value!r}", f"use one of {', '.join(RULES)}")
    return rule
