"""CQL2 filters (cql2-text and cql2-json) as SQL on the catalog index.

Parsing is the ``cql2`` package's (PyPI; it reads both encodings and normalises them to cql2-json);
this module only walks the parsed JSON tree and writes a parameterised SQL expression over
``items AS i`` (:mod:`archive.catalog.index`). What it translates:

- logic: ``and``, ``or``, ``not``; ``isNull``;
- comparisons ``=``, ``<>``, ``<``, ``<=``, ``>``, ``>=``, and ``like`` (case-sensitive, ``%`` and
  ``_``), ``between``, ``in``;
- ``s_intersects`` of ``geometry`` with a GeoJSON geometry or a ``BBOX(w, s, e, n)``: the footprint
  itself, exactly (R*Tree, then shapely), as the ``bbox`` and ``intersects`` search parameters;
- temporal operators ``t_*`` of ``datetime`` (the flight's interval [start_datetime, end_datetime])
  with a TIMESTAMP, DATE or INTERVAL (``'..'`` open ends).

Properties (the queryables, :data:`QUERYABLES`): ``id``, ``collection``, ``datetime`` (=
``start_datetime``), ``start_datetime``, ``end_datetime``, ``hsi:wavelength_min``,
``hsi:wavelength_max`` (nm), ``gsd`` (m), ``archive:bands``, ``geometry``. Any other property
name is null for every Item (the queryables allow additional properties), so ``eo:cloud_cover < 10``
matches nothing and ``eo:cloud_cover IS NULL`` everything. Unsupported parts (arithmetic,
functions, array operators, property-property temporal tests) are an InputError naming them.
"""

from __future__ import annotations

import math
import re
import threading
from datetime import UTC, date, datetime, time, timedelta
from typing import Any

from archive.errors import InputError

#: Queryable property -> (SQL expression on ``items AS i``, JSON schema of its values).
QUERYABLES: dict[str, tuple[str, dict]] = {
    "id": ("i.id", {"title": "Item id (collection id)", "type": "string"}),
    "collection": ("'flights'", {"title": "Collection", "type": "string", "enum": ["flights"]}),
    "datetime": ("i.start_time", {"title": "Start of the flight (UTC)", "type": "string", "format": "date-time"}),
    "start_datetime": ("i.start_time", {"title": "First line (UTC)", "type": "string", "format": "date-time"}),
    "end_datetime": ("i.end_time", {"title": "Last line (UTC)", "type": "string", "format": "date-time"}),
    "hsi:wavelength_min": ("i.min_wavelength", {"title": "Shortest band centre", "type": "number",
                                                "unit": "nm"}),
    "hsi:wavelength_max": ("i.max_wavelength", {"title": "Longest band centre", "type": "number", "unit": "nm"}),
    "gsd": ("i.gsd", {"title": "Nominal ground sample distance", "type": "number", "unit": "m"}),
    "archive:bands": ("i.bands", {"title": "Number of bands", "type": "integer"}),
    "geometry": ("", {"title": "Footprint", "$ref": "https://geojson.org/schema/Geometry.json"}),
}
#: Properties whose values are instants (compared as epoch seconds).
TEMPORAL = {"datetime", "start_datetime", "end_datetime"}
_COMPARISONS = {"=": "=", "<>": "<>", "<": "<", "<=": "<=", ">": ">", ">=": ">="}
#: Temporal operators on the Item interval [s, e] and the query interval [a, b] (an instant: a = b).
_TEMPORAL_OPS: dict[str, str] = {
    "t_after": "s > b", "t_before": "e < a", "t_contains": "s < a AND b < e", "t_disjoint": "NOT (s <= b AND e >= a)",
    "t_during": "a < s AND e < b", "t_equals": "s = a AND e = b", "t_finishedby": "s < a AND e = b",
    "t_finishes": "a < s AND e = b", "t_intersects": "s <= b AND e >= a", "t_meets": "e = a", "t_metby": "s = b",
    "t_overlappedby": "a < s AND s < b AND b < e", "t_overlaps": "s < a AND a < e AND e < b",
    "t_startedby": "s = a AND b < e", "t_starts": "s = a AND e < b",
}
MAX_FILTER_CHARS = 100_000
#: Deepest nesting of parentheses/brackets (cql2-text) or of objects/arrays (JSON) parsed at all.
MAX_NESTING = 64
#: Most prefix and arithmetic operators (NOT, +, -, *, /, %, ^, DIV) in a cql2-text filter outside
#: geometry literals: each may add a level to the parse tree (a chain of 5,000 ``NOT`` overflows the
#: stack of the ``cql2`` parser, a native library: the process dies, no exception).
MAX_OPERATORS = 200
#: Most JSON values (objects, arrays, scalars) in a cql2-json filter or a request body.
MAX_JSON_VALUES = 200_000
#: Deepest expression tree translated to SQL (levels of and/or/not/operators).
MAX_TREE_DEPTH = 96
#: Stack of the thread that runs the cql2 parser: far more than the bounded inputs need (a last
#: line of defence: a native stack overflow cannot be caught).
PARSER_STACK_BYTES = 256 << 20

_GEOMETRY_WORDS = {"POINT", "LINESTRING", "POLYGON", "MULTIPOINT", "MULTILINESTRING", "MULTIPOLYGON",
                   "GEOMETRYCOLLECTION", "BBOX", "ENVELOPE"}
_TEXT_TOKEN = re.compile(r"'(?:[^']|'')*'?|\"(?:[^\"]|\"\")*\"?|[A-Za-z_][A-Za-z0-9_:.]*|\d[\d.]*(?:[eE][+-]?\d+)?"
                         r"|<>|<=|>=|\S")
_JSON_STRUCT = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]|[^\s"\[\]{},:]+')


def check_text(text: str, name: str = "filter") -> None:
    """Bound a cql2-text filter before any parser sees it: its length (MAX_FILTER_CHARS), the
    nesting of its parentheses (MAX_NESTING) and its count of prefix/arithmetic operators outside
    geometry literals (MAX_OPERATORS). InputError naming ``name`` otherwise."""
    if len(text) > MAX_FILTER_CHARS:
        raise InputError(name, f"{len(text)} characters is too long (at most {MAX_FILTER_CHARS})",
                         "give a shorter filter; a large geometry goes in 'intersects'")
    depth = operators = 0
    geometry_depth = None  # the depth at which the geometry literal being read opened
    pending_geometry = False
    for match in _TEXT_TOKEN.finditer(text):
        token = match.group(0)
        if token in ("(", "["):
            depth += 1
            if depth > MAX_NESTING:
                raise InputError(name, f"nested more than {MAX_NESTING} levels deep",
                                 "simplify the filter (fewer nested parentheses)")
            if pending_geometry and geometry_depth is None:
                geometry_depth = depth
            pending_geometry = False
            continue
        if token in (")", "]"):
            if geometry_depth is not None and depth == geometry_depth:
                geometry_depth = None
            depth = max(depth - 1, 0)
            continue
        pending_geometry = token.upper() in _GEOMETRY_WORDS
        if geometry_depth is None and (token.upper() in ("NOT", "DIV") or token in "+-*/%^"):
            operators += 1
            if operators > MAX_OPERATORS:
                raise InputError(name, f"more than {MAX_OPERATORS} NOT or arithmetic operators",
                                 "simplify the filter")


def check_json_text(text: str | bytes, name: str, max_chars: int = MAX_FILTER_CHARS) -> None:
    """Bound a JSON document before it is parsed: its size (``max_chars``), the nesting of its
    objects and arrays (MAX_NESTING) and its number of values (MAX_JSON_VALUES)."""
    if isinstance(text, bytes | bytearray):
        text = bytes(text).decode("utf-8", errors="replace")
    if len(text) > max_chars:
        raise InputError(name, f"{len(text)} characters is too long (at most {max_chars})")
    depth = values = 0
    for match in _JSON_STRUCT.finditer(text):
        token = match.group(0)
        if token in ("[", "{"):
            depth += 1
            if depth > MAX_NESTING:
                raise InputError(name, f"JSON nested more than {MAX_NESTING} levels deep", "simplify it")
        elif token in ("]", "}"):
            depth = max(depth - 1, 0)
        values += 1
        if values > MAX_JSON_VALUES:
            raise InputError(name, f"more than {MAX_JSON_VALUES} JSON values", "give a smaller document")


def check_tree(node: Any, name: str = "filter", max_depth: int = MAX_NESTING) -> None:
    """Bound a parsed JSON value (dicts, lists, scalars) without recursion: depth at most
    ``max_depth``, at most MAX_JSON_VALUES values, numbers finite and integers within 64 bits.
    InputError naming ``name`` and the key path of the offending value otherwise."""
    stack: list[tuple[Any, int, str]] = [(node, 1, "")]
    values = 0
    while stack:
        value, depth, path = stack.pop()
        values += 1
        if values > MAX_JSON_VALUES:
            raise InputError(name, f"more than {MAX_JSON_VALUES} JSON values", "give a smaller document")
        where = f"{path.lstrip('.')}: " if path else ""
        if isinstance(value, dict | list):
            if depth > max_depth:
                raise InputError(name, f"nested more than {max_depth} levels deep", "simplify it")
            items = value.items() if isinstance(value, dict) else enumerate(value)
            stack.extend((c, depth + 1, f"{path}.{str(k)[:40]}" if depth < 4 else path) for k, c in items)
        elif isinstance(value, float) and not math.isfinite(value):
            raise InputError(name, f"{where}{value} is not a finite number")
        elif isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2 ** 63 - 1:
            raise InputError(name, f"{where}the integer {str(value)[:20]}... is out of range (at most 2**63 - 1)")


def _parse_guarded(filter_value: Any) -> dict:
    """cql2's parse (text or JSON) of a bounded input, in a thread with a large stack."""
    import cql2

    result: dict[str, Any] = {}

    def work() -> None:
        try:
            result["tree"] = cql2.Expr(filter_value).to_json()
        except BaseException as exc:  # cql2 raises ValueError/ParseError/plain Exception, or RecursionError
            result["error"] = exc

    with _STACK_LOCK:
        previous = threading.stack_size(PARSER_STACK_BYTES)
        try:
            worker = threading.Thread(target=work, name="archive-cql2", daemon=True)
            worker.start()
        finally:
            threading.stack_size(previous)
    worker.join()
    if "error" in result:
        exc = result["error"]
        first = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise InputError("filter", f"not a CQL2 expression: {first}",
                         "see https://docs.ogc.org/is/21-065r2/21-065r2.html, e.g. "
                         "\"hsi:wavelength_min <= 650 AND hsi:wavelength_max >= 650\"")
    return result["tree"]


_STACK_LOCK = threading.Lock()


def parse(filter_value: Any, lang: str | None = None) -> dict:
    """The cql2-json tree of a filter given as cql2-text (a string) or cql2-json (a dict, or a
    JSON string with ``lang='cql2-json'``); InputError naming ``filter`` when it does not parse.
    The input is bounded first (:func:`check_text`, :func:`check_json_text`, :func:`check_tree`),
    so that nothing oversized or deeply nested reaches the parser."""
    if lang not in (None, "cql2-text", "cql2-json"):
        raise InputError("filter-lang", f"{str(lang)[:40]!r} is not supported", "use cql2-text or cql2-json")
    if isinstance(filter_value, str):
        if lang == "cql2-json" or (lang is None and filter_value.lstrip().startswith("{")):
            import json

            check_json_text(filter_value, "filter")
            try:
                filter_value = json.loads(filter_value)
            except (ValueError, RecursionError) as exc:
                raise InputError("filter", f"not JSON: {str(exc)[:200]}",
                                 "give cql2-json, or filter-lang=cql2-text") from None
            if not isinstance(filter_value, dict):
                raise InputError("filter", "cql2-json must be a JSON object")
        else:
            check_text(filter_value)
    elif not isinstance(filter_value, dict):
        raise InputError("filter", f"expected cql2-text (a string) or cql2-json (an object), got "
                                   f"{type(filter_value).__name__}")
    if isinstance(filter_value, dict):
        check_tree(filter_value)
    tree = _parse_guarded(filter_value)
    check_tree(tree, max_depth=MAX_TREE_DEPTH * 2 + 8)  # {op, args: [...]}: two JSON levels a level
    return tree


class Translator:
    """Writes one filter tree as SQL; ``params`` collects the values in order."""

    def __init__(self):
        self.params: list[Any] = []

    # ---- values ------------------------------------------------------------------------------
    def _value(self, node: Any, temporal: bool = False) -> Any:
        if isinstance(node, dict):
            if "timestamp" in node:
                return _instant(node["timestamp"], end=False)
            if "date" in node:
                return _instant(node["date"], end=False)
            raise InputError("filter", f"expected a literal value, got {_short(node)}",
                             "compare properties with numbers, strings, TIMESTAMP() or DATE()")
        if isinstance(node, bool) or node is None:
            return node
        if isinstance(node, int | float):
            if not math.isfinite(node):
                raise InputError("filter", f"{node} is not a finite number")
            return node
        if isinstance(node, str):
            return _instant(node, end=False) if temporal else node
        raise InputError("filter", f"expected a literal value, got {_short(node)}")

    def _property(self, node: Any) -> str | None:
        if isinstance(node, dict) and set(node) == {"property"}:
            return str(node["property"]).removeprefix("properties.")
        return None

    def _operand(self, node: Any) -> tuple[str, bool]:
        """(SQL, is temporal) of a property or a literal."""
        name = self._property(node)
        if name is not None:
            if name == "geometry":
                raise InputError("filter", "geometry can only be tested with S_INTERSECTS")
            sql = QUERYABLES.get(name, ("NULL", {}))[0]
            return sql, name in TEMPORAL
        if isinstance(node, dict) and "op" in node:
            raise InputError("filter", f"operator {node['op']!r} is not supported as a value",
                             "arithmetic and functions are not supported")
        self.params.append(self._value(node))
        return "?", isinstance(node, dict) and ("timestamp" in node or "date" in node)

    def _pair(self, args: list) -> tuple[str, str]:
        if len(args) != 2:
            raise InputError("filter", f"a comparison takes 2 arguments, got {len(args)}")
        # a temporal property compared with a string literal reads it as an instant
        left_prop, right_prop = self._property(args[0]), self._property(args[1])
        left = self._operand(args[0]) if not (right_prop in TEMPORAL and isinstance(args[0], str)) else \
            self._literal(args[0], True)
        right = self._operand(args[1]) if not (left_prop in TEMPORAL and isinstance(args[1], str)) else \
            self._literal(args[1], True)
        return left[0], right[0]

    def _literal(self, node, temporal: bool) -> tuple[str, bool]:
        self.params.append(self._value(node, temporal))
        return "?", temporal

    # ---- the tree ----------------------------------------------------------------------------
    def sql(self, node: Any) -> str:
        if isinstance(node, bool):
            return "1" if node else "0"
        if not isinstance(node, dict) or "op" not in node:
            raise InputError("filter", f"expected a boolean expression, got {_short(node)}")
        op = str(node["op"]).lower()
        args = node.get("args") or []
        if op in ("and", "or"):
            if not args:
                raise InputError("filter", f"{op} needs arguments")
            return "(" + f" {op.upper()} ".join(self.sql(a) for a in args) + ")"
        if op == "not":
            if len(args) != 1:
                raise InputError("filter", f"not takes 1 argument, got {len(args)}")
            return f"(NOT {self.sql(args[0])})"
        if op in _COMPARISONS:
            left, right = self._pair(args)
            return f"({left} {_COMPARISONS[op]} {right})"
        if op == "isnull":
            if len(args) != 1:
                raise InputError("filter", f"isNull takes 1 argument, got {len(args)}")
            return f"({self._operand(args[0])[0]} IS NULL)"
        if op == "like":
            if len(args) != 2 or not isinstance(args[1], str):
                raise InputError("filter", "LIKE takes a property and a pattern string")
            target = self._operand(args[0])[0]
            self.params.append(_glob(args[1]))
            return f"({target} GLOB ?)"
        if op == "between":
            bounds = args[1] if len(args) == 2 and isinstance(args[1], list) else args[1:]
            if len(bounds) != 2:
                raise InputError("filter", "BETWEEN takes a property and two bounds")
            name = self._property(args[0])
            target = self._operand(args[0])[0]
            temporal = name in TEMPORAL
            low, high = (self._literal(b, temporal)[0] for b in bounds)
            return f"({target} BETWEEN {low} AND {high})"
        if op == "in":
            if len(args) != 2 or not isinstance(args[1], list) or not args[1]:
                raise InputError("filter", "IN takes a property and a non-empty list")
            temporal = self._property(args[0]) in TEMPORAL
            target = self._operand(args[0])[0]
            marks = ", ".join(self._literal(v, temporal)[0] for v in args[1])
            return f"({target} IN ({marks}))"
        if op == "s_intersects":
            return self._spatial(args)
        if op in _TEMPORAL_OPS:
            return self._temporal(op, args)
        raise InputError("filter", f"operator {node['op']!r} is not supported",
                         "supported: and, or, not, =, <>, <, <=, >, >=, isNull, like, between, in, s_intersects, "
                         "t_* (temporal)")

    def _spatial(self, args: list) -> str:
        from archive.catalog.index import geometry_wkb, spatial_clause

        if len(args) != 2:
            raise InputError("filter", f"S_INTERSECTS takes 2 arguments, got {len(args)}")
        geom = args[1] if self._property(args[0]) == "geometry" else args[0]
        if self._property(args[0]) != "geometry" and self._property(args[1]) != "geometry":
            raise InputError("filter", "S_INTERSECTS tests the property geometry against a geometry")
        if isinstance(geom, dict) and "bbox" in geom:
            box = parse_bbox_values(geom["bbox"], "filter")
            return self._spatial_boxes(box)
        if not isinstance(geom, dict) or "type" not in geom:
            raise InputError("filter", f"S_INTERSECTS needs a geometry literal, got {_short(geom)}")
        wkb = geometry_wkb(geom)
        import shapely

        bounds = shapely.from_wkb(wkb).bounds
        clause, params = spatial_clause(bounds, wkb)
        self.params += params
        return clause

    def _spatial_boxes(self, box) -> str:
        from archive.catalog.index import spatial_clause

        parts = []
        for b in split_antimeridian(box):
            clause, params = spatial_clause(b)
            self.params += params
            parts.append(clause)
        return "(" + " OR ".join(parts) + ")"

    def _temporal(self, op: str, args: list) -> str:
        if len(args) != 2:
            raise InputError("filter", f"{op.upper()} takes 2 arguments, got {len(args)}")
        name = self._property(args[0])
        if name not in TEMPORAL:
            raise InputError("filter", f"{op.upper()} tests datetime, start_datetime or end_datetime against a "
                                       "TIMESTAMP, DATE or INTERVAL")
        if name == "datetime":
            s, e = "i.start_time", "i.end_time"
        else:
            s = e = QUERYABLES[name][0]
        lit = args[1]
        if isinstance(lit, dict) and "interval" in lit:
            ends = lit["interval"]
            if not isinstance(ends, list) or len(ends) != 2:
                raise InputError("filter", "an INTERVAL has two ends")
            a = -math.inf if _open(ends[0]) else _instant(_text_of(ends[0]), end=False)
            b = math.inf if _open(ends[1]) else _instant(_text_of(ends[1]), end=True)
        elif isinstance(lit, dict) and ("timestamp" in lit or "date" in lit):
            a = _instant(lit.get("timestamp") or lit.get("date"), end=False)
            b = a if "timestamp" in lit else _instant(lit["date"], end=True)
        else:
            raise InputError("filter", f"{op.upper()} needs a TIMESTAMP, DATE or INTERVAL, got {_short(lit)}")
        import re

        def term(match) -> str:
            token = match.group(0)
            if token in ("s", "e"):
                return s if token == "s" else e
            self.params.append(max(min(a if token == "a" else b, 1e300), -1e300))  # open ends: +-inf
            return "?"

        sql = re.sub(r"\b[abse]\b", term, _TEMPORAL_OPS[op])
        return f"({sql})"


def to_sql(tree: dict) -> tuple[str, list]:
    """(SQL boolean expression over ``items AS i``, its parameters) of a cql2-json tree."""
    t = Translator()
    return t.sql(tree), t.params


def queryables_schema(url: str) -> dict:
    """The queryables document (JSON Schema) served at ``url``."""
    return {
        "$schema": "https://json-schema.org/draft/2019-09/schema",
        "$id": url,
        "type": "object",
        "title": "Queryables of the archive's flights",
        "description": "Properties a CQL2 filter may name; any other name is null for every Item.",
        "properties": {name: dict(schema) for name, (_, schema) in QUERYABLES.items()},
        "additionalProperties": True,
    }


# ---- helpers ----------------------------------------------------------------------------------
def _short(node: Any) -> str:
    text = repr(node)
    return text if len(text) <= 80 else text[:77] + "..."


def _open(end: Any) -> bool:
    return end is None or end == ".." or end == ""


def _text_of(end: Any) -> str:
    if isinstance(end, dict):
        end = end.get("timestamp") or end.get("date")
    if not isinstance(end, str):
        raise InputError("filter", f"an INTERVAL end must be a date or timestamp, got {_short(end)}")
    return end


def _instant(text: Any, end: bool) -> float:
    """Epoch seconds of an RFC 3339 timestamp or a date (a date's end: its last microsecond)."""
    if not isinstance(text, str):
        raise InputError("filter", f"expected a date or timestamp, got {_short(text)}")
    try:
        if len(text) == 10:
            moment = datetime.combine(date.fromisoformat(text), time(0), tzinfo=UTC)
            if end:
                moment += timedelta(days=1) - timedelta(microseconds=1)
        else:
            moment = datetime.fromisoformat(text.replace("Z", "+00:00").replace("z", "+00:00"))
            if moment.tzinfo is None:
                moment = moment.replace(tzinfo=UTC)
    except ValueError:
        raise InputError("filter", f"{text!r} is not an RFC 3339 date or timestamp") from None
    return moment.timestamp()


def _glob(pattern: str) -> str:
    """A CQL2 LIKE pattern (``%``, ``_``, backslash escapes) as a case-sensitive SQLite GLOB."""
    out, escaped = [], False
    for ch in pattern:
        if escaped:
            out.append(f"[{ch}]" if ch in "*?[" else ch)
            escaped = False
        elif ch == "\\":
            escaped = True
        elif ch == "%":
            out.append("*")
        elif ch == "_":
            out.append("?")
        elif ch in "*?[":
            out.append(f"[{ch}]")
        else:
            out.append(ch)
    return "".join(out)


def parse_bbox_values(values: Any, name: str = "bbox") -> tuple[float, float, float, float]:
    """[w, s, e, n] or [w, s, zmin, e, n, zmax] degrees -> (w, s, e, n); west may exceed east (a
    box across the antimeridian)."""
    if not isinstance(values, list | tuple) or len(values) not in (4, 6):
        raise InputError(name, f"expected 4 (or 6) numbers, got {_short(values)}",
                         "give west,south,east,north in degrees")
    try:
        nums = [float(v) for v in values]
    except (TypeError, ValueError):
        raise InputError(name, f"expected numbers, got {_short(values)}") from None
    if len(nums) == 6:
        nums = [nums[0], nums[1], nums[3], nums[4]]
    w, s, e, n = nums
    if not all(math.isfinite(v) for v in nums):
        raise InputError(name, "values must be finite")
    if not (-180 <= w <= 180 and -180 <= e <= 180 and -90 <= s <= n <= 90):
        raise InputError(name, f"{nums} is out of range (longitude -180..180, latitude -90..90, south <= north)")
    return (w, s, e, n)


def split_antimeridian(box) -> list[tuple[float, float, float, float]]:
    """One box, or two when west > east (across the antimeridian)."""
    w, s, e, n = box
    return [(w, s, e, n)] if w <= e else [(w, s, 180.0, n), (-180.0, s, e, n)]

