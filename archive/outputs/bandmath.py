"""Spectral indices: named ones from the Awesome Spectral Indices catalogue (``spyndex``) and
``NAME=EXPR`` band math, mapped to a camera's bands by wavelength and evaluated without ``eval``.

**Named indices** (``NDVI``, ``EVI``, ... any of :func:`catalogue_names`): the catalogue's formula,
whose band symbols (``N``, ``R``, ``RE1``...) each take the camera band **nearest the centre of the
catalogue's wavelength range** for that symbol (``R``: 620-690 nm -> the band nearest 655 nm),
refused when that band lies outside the range (an 8-band 400-1000 nm camera has no ``RE1``,
695-715 nm). Constants (``L``, ``g``, ``C1``...) take the catalogue's defaults; ``lambdaX`` is the
chosen band's wavelength (nm). One band per symbol, not the mean over the range: the same band a
user would pick, two bands read for NDVI whatever the camera. The mapping is recorded per index
(:attr:`BoundIndex.bands`, the table's ``bands`` column).

**Expressions** ``NAME=EXPR``: ``R<nm>`` is the reflectance (or the mode's value) of the band
nearest ``<nm>`` nm, refused when no band lies within half the camera's band spacing (its median
step) of ``<nm>``; numbers, ``+ - * / **``, unary ``-``/``+``, parentheses and the functions
:data:`FUNCTIONS` (``sqrt``, ``abs``, ``exp``, ``log``, ``log10``, ``min``, ``max``). The text is
parsed with :mod:`ast` and every node checked against that whitelist: names, attributes,
subscripts, calls of anything else, keywords and comparisons are refused in one line. Evaluation
walks the checked tree over numpy arrays (float32 in, float32 out; non-finite results NaN).

Axis order: values are arrays of any one shape (a window is (y, x)); wavelengths in nm.

Here, below the writers, because ``archive render --index`` computes the indices per written tile
(:mod:`archive.outputs.indexed`); :mod:`archive.analysis.indices` re-exports it for ``archive stats``.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from archive.errors import InputError

__all__ = ["FUNCTIONS", "BoundIndex", "IndexSpec", "band_spacing", "bind_indices", "catalogue_names", "evaluate",
           "index_env", "named_index", "nearest_band", "parse_expression", "parse_indices", "walk_index"]

#: The functions an expression may call (elementwise, over numpy arrays).
FUNCTIONS = {"sqrt": np.sqrt, "abs": np.abs, "exp": np.exp, "log": np.log, "log10": np.log10,
             "min": np.minimum, "max": np.maximum}
#: Longest expression text accepted (characters): bounded before it is parsed.
MAX_EXPRESSION = 1000
_OPS = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.divide, ast.Pow: np.power}
_UNARY = {ast.USub: np.negative, ast.UAdd: np.positive}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.+-]{0,63}$")
_BAND = re.compile(r"^R(\d{2,5})$")


@dataclass(frozen=True)
class IndexSpec:
    """An index asked for, before it meets a camera: its ``name`` (the table's ``index``), the
    formula ``text``, its checked tree, and where it comes from (``catalogue``: True for a named
    index). ``symbols``: the band symbols the formula reads (catalogue letters such as ``N``, or
    ``R<nm>``), in order of first use; ``constants``: the catalogue's default values it uses."""

    name: str
    text: str
    tree: ast.Expression = field(repr=False, compare=False)
    catalogue: bool
    symbols: tuple[str, ...]
    constants: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class BoundIndex:
    """An index on a camera: ``spec`` and, per band symbol, the camera band's wavelength (nm)
    (``bands``: symbol -> nm, in the order the symbols are used)."""

    spec: IndexSpec
    bands: tuple[tuple[str, float], ...]

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def wavelengths(self) -> tuple[float, ...]:
        """The camera bands (nm) this index reads."""
        return tuple(dict.fromkeys(nm for _, nm in self.bands))

    def describe(self) -> str:
        """'N=828.6nm,R=657.1nm': which band each symbol took (the table's ``bands`` column)."""
        return ",".join(f"{s}={nm:.1f}nm" for s, nm in self.bands)


# ---------------------------------------------------------------------------------------------
# Parsing (no camera needed)
# ---------------------------------------------------------------------------------------------
def _check_tree(text: str, where: str, allowed_name) -> tuple[ast.Expression, list[str]]:
    """The parsed, whitelisted tree of ``text`` and the names it uses (in order); InputError naming
    ``where`` for anything else. ``allowed_name(name)``: whether a bare name may stand (a band or a
    constant)."""
    if len(text) > MAX_EXPRESSION:
        raise InputError(where, f"the expression is {len(text)} characters long, at most {MAX_EXPRESSION}")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        why = getattr(exc, "msg", None) or type(exc).__name__
        raise InputError(where, f"cannot parse {text!r}: {why}", "write e.g. NDVI2=(R800-R670)/(R800+R670)") from None
    names: list[str] = []

    def check(node: ast.AST) -> None:
        if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
            check(node.left)
            check(node.right)
        elif isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            check(node.operand)
        elif isinstance(node, ast.Constant) and type(node.value) in (int, float):
            pass
        elif isinstance(node, ast.Name):
            if not allowed_name(node.id):
                raise InputError(where, f"{node.id!r} is not a band: write R<nm> for the band nearest <nm> nm "
                                 "(R670, R800)")
            names.append(node.id)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FUNCTIONS
              and not node.keywords and node.args):
            for arg in node.args:
                check(arg)
        else:
            what = ast.unparse(node) if hasattr(ast, "unparse") else type(node).__name__
            raise InputError(where, f"{what!r} is not allowed in an expression",
                             f"use numbers, R<nm> bands, + - * / ** and {', '.join(FUNCTIONS)}")

    try:
        check(tree.body)
    except RecursionError:
        raise InputError(where, "the expression is nested too deeply") from None
    return tree, list(dict.fromkeys(names))


def parse_expression(text: str) -> IndexSpec:
    """``NAME=EXPR`` (``--expression``) checked: InputError in one line for a missing name, a bad
    name, text that does not parse or uses anything but the whitelist. ``R<nm>`` bands only."""
    where = "--expression"
    name, sep, expr = str(text).partition("=")
    name = name.strip()
    if not sep or not expr.strip():
        raise InputError(where, f"expected NAME=EXPR, got {text!r}", "e.g. --expression 'NDVI2=(R800-R670)/(R800+R670)'")
    if not _NAME.match(name):
        raise InputError(where, f"{name!r} is not a name for an index (letters, digits, _ . + -, starting with "
                         "a letter)")
    tree, names = _check_tree(expr, f"{where} {name}", lambda n: bool(_BAND.match(n)))
    if not names:
        raise InputError(f"{where} {name}", f"{expr.strip()!r} reads no band", "use R<nm>, e.g. R800")
    return IndexSpec(name, expr.strip(), tree, False, tuple(names))


def catalogue_names() -> list[str]:
    """Names of the catalogue's indices (spyndex's Awesome Spectral Indices), sorted."""
    import spyndex

    return sorted(spyndex.indices.keys())


def named_index(name: str) -> IndexSpec:
    """The catalogue's index ``name`` (case as the catalogue spells it; a case-insensitive match is
    taken); InputError in one line naming the nearest names for an unknown one."""
    import difflib

    import spyndex

    indices = spyndex.indices
    key = name if name in indices else {k.lower(): k for k in indices}.get(str(name).lower())
    if key is None:
        near = difflib.get_close_matches(str(name), list(indices), n=3)
        hint = f"did you mean {', '.join(near)}?" if near else "see docs/stats.md for the catalogue"
        raise InputError("--index", f"unknown spectral index {name!r} ({len(indices)} in the catalogue; {hint})",
                         "or give band math with --expression NAME=EXPR")
    index = indices[key]
    bands, constants = set(spyndex.bands.keys()), spyndex.constants
    symbols, values = [], []
    for s in index.bands:
        if s in bands:
            symbols.append(s)
        elif s.startswith("lambda") and s[len("lambda"):] in bands:
            continue   # a band's wavelength: the chosen band's, at binding
        elif s in constants and constants[s].default is not None:
            values.append((s, float(constants[s].default)))
        else:
            raise InputError("--index", f"{key} needs {s!r}, which neither a camera band nor a default constant "
                             "gives", "write it as --expression NAME=EXPR with the value you want")
    lambdas = [s[len("lambda"):] for s in index.bands if s.startswith("lambda") and s[len("lambda"):] in bands]
    symbols += [s for s in lambdas if s not in symbols]
    allowed = set(index.bands)
    tree, _ = _check_tree(index.formula, f"--index {key}", lambda n: n in allowed)
    return IndexSpec(key, index.formula, tree, True, tuple(symbols), tuple(values))


def parse_indices(names: Sequence[str] = (), expressions: Sequence[str] = ()) -> list[IndexSpec]:
    """The indices of ``--index`` names and ``--expression`` texts, checked (no camera needed);
    InputError for none at all or a name given twice."""
    specs = [named_index(n) for n in names] + [parse_expression(e) for e in expressions]
    if not specs:
        raise InputError("--index", "no index asked for", "pass --index NDVI and/or --expression NAME=EXPR")
    seen: set[str] = set()
    for s in specs:
        if s.name in seen:
            raise InputError("--index", f"{s.name} is asked for twice", "give each index once, or rename an expression")
        seen.add(s.name)
    return specs


# ---------------------------------------------------------------------------------------------
# Binding to a camera
# ---------------------------------------------------------------------------------------------
def band_spacing(wavelengths: Sequence[float]) -> float:
    """The camera's band spacing, nm: the median step between neighbouring band centres (inf for one band)."""
    wl = np.sort(np.asarray(wavelengths, float))
    return float(np.median(np.diff(wl))) if wl.size > 1 else math.inf


def bind_indices(specs: Sequence[IndexSpec], wavelengths: Sequence[float] | None, camera: str = "the camera") -> list[BoundIndex]:
    """``specs`` on a camera of band centres ``wavelengths`` (nm): each symbol's band chosen (see the
    module docstring); InputError naming the index, the symbol and the bands there are when none fits."""
    import spyndex

    if wavelengths is None or not len(wavelengths):
        raise InputError(camera, "records no band wavelengths, so no index can be mapped to its bands",
                         "ingest the flight with its headers' wavelengths")
    wl = np.asarray(wavelengths, float)
    spacing = band_spacing(wl)
    span = f"{wl.min():.0f}-{wl.max():.0f} nm, {wl.size} bands"
    out = []
    for spec in specs:
        chosen = []
        for s in spec.symbols:
            if spec.catalogue:
                b = spyndex.bands[s]
                lo, hi = float(b.min_wavelength), float(b.max_wavelength)
                nm = float(wl[np.argmin(np.abs(wl - (lo + hi) / 2))])
                if not lo <= nm <= hi:
                    raise InputError(f"--index {spec.name}", f"needs {s} ({b.long_name}, {lo:g}-{hi:g} nm) but "
                                     f"{camera} has no band there ({span})", "pick another index, or band math "
                                     "with --expression")
            else:
                want = float(_BAND.match(s).group(1))
                nm = float(wl[np.argmin(np.abs(wl - want))])
                if abs(nm - want) > spacing / 2:
                    raise InputError(f"--expression {spec.name}", f"{s}: no band of {camera} within half a band "
                                     f"spacing ({spacing / 2:.1f} nm) of {want:g} nm ({span})",
                                     "use a wavelength the camera records")
            chosen.append((s, nm))
        out.append(BoundIndex(spec, tuple(chosen)))
    return out


def walk_index(index: BoundIndex, env: Mapping[str, object]):
    """The checked tree of ``index`` over ``env`` (symbol -> array: numpy, or a lazy xarray/dask one:
    numpy's ufuncs keep them lazy)."""
    def walk(node: ast.AST):
        if isinstance(node, ast.BinOp):
            return _OPS[type(node.op)](walk(node.left), walk(node.right))
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](walk(node.operand))
        if isinstance(node, ast.Constant):
            return np.float32(node.value)
        if isinstance(node, ast.Name):
            return env[node.id]
        if isinstance(node, ast.Call):
            args = [walk(a) for a in node.args]
            func = FUNCTIONS[node.func.id]
            if func in (np.minimum, np.maximum):
                result = args[0]
                for a in args[1:]:
                    result = func(result, a)
                return result
            return func(*args)
        raise AssertionError(type(node))   # the tree was checked when parsed

    return walk(index.spec.tree.body)


def index_env(index: BoundIndex, band) -> dict[str, object]:
    bands = dict(index.bands)
    env: dict[str, object] = {s: band(nm) for s, nm in bands.items()}
    env.update({f"lambda{s}": np.float32(nm) for s, nm in bands.items()})
    env.update({k: np.float32(v) for k, v in index.spec.constants})
    return env


def nearest_band(index: BoundIndex, nms: np.ndarray, nm: float) -> int:
    """The position in ``nms`` of the band centred at ``nm`` (a float32 copy of a centre may differ by ulps)."""
    k = int(np.argmin(np.abs(nms - nm))) if nms.size else -1
    if k < 0 or abs(nms[k] - nm) > 0.01:
        raise InputError(index.name, f"needs the band at {nm:.3f} nm, which the values lack")
    return k


def evaluate(index: BoundIndex, values: Mapping[float, np.ndarray]) -> np.ndarray:
    """The index from ``values`` (camera band wavelength nm -> array, one shape; a band is found
    within 0.01 nm of its centre), float32, NaN where a band is NaN or the formula has no finite
    value (0/0, a log of a negative)."""
    given = list(values)
    nms = np.asarray(given, float)
    env = index_env(index, lambda nm: np.asarray(values[given[nearest_band(index, nms, nm)]], np.float32))
    with np.errstate(all="ignore"):
        out = np.asarray(walk_index(index, env), np.float32)
    shape = np.broadcast_shapes(*(np.shape(v) for v in values.values())) if values else ()
    out = np.broadcast_to(out, shape).astype(np.float32, copy=True)
    out[~np.isfinite(out)] = np.nan
    return out
