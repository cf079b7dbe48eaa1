"""The package's structure (DESIGN 1), read from the source: no import cycles among archive
modules, no private (``_name``) import from another archive module, no private member of another
archive module used, dependencies pointing down the layers, moderngl only in ``render/`` (and the
light entry points importing without it), and ``graph/`` never computing.

The import graph is read from the source with ``ast`` (no module is imported), every ``import`` and
``from ... import`` counted, those inside functions included:

- ``import a.b.c`` (and ``importlib.import_module("a.b.c")`` with a literal name) imports ``a.b.c``;
  ``from a.b import c`` imports ``a.b.c`` when ``c`` is a submodule, else ``a.b`` itself; relative
  imports are resolved against the importer's package.
- Importing ``a.b.c`` first runs the ``__init__`` of the packages ``a`` and ``a.b``: those count as
  edges too, except for packages that enclose the importer (Python has already started them before
  the importer runs). ``from a.b import name`` needs ``a.b`` fully initialised, so it counts even
  from inside ``a.b``: that is how a package's ``__init__`` and its submodules end up in a cycle.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "archive"


@dataclass(frozen=True)
class Edge:
    """``source`` imports ``target`` at ``path:line``; ``names`` the names a ``from`` import takes."""

    source: str
    target: str
    path: Path
    line: int
    names: tuple[str, ...] = ()


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    """Every module of the package (``archive.x.y`` -> file); packages by their ``__init__``."""
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py")) if "__pycache__" not in p.parts}


def _parents(name: str) -> list[str]:
    """Enclosing packages of a dotted name, outermost first: a.b.c -> [a, a.b]."""
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _package_of(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _resolve(node: ast.ImportFrom, name: str, path: Path) -> str:
    if not node.level:
        return node.module or ""
    base = _package_of(name, path).split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_edges(mods: dict[str, Path] | None = None) -> list[Edge]:
    """Every import of every archive module that names an archive module (see the module docstring)."""
    mods = modules() if mods is None else mods
    edges: list[Edge] = []
    for name, path in mods.items():
        enclosing = set(_parents(name)) | ({name} if path.name == "__init__.py" else set())

        def add(target: str, line: int, names: tuple[str, ...] = (), explicit: bool = True) -> None:
            for parent in _parents(target):
                if parent in mods and parent not in enclosing:
                    edges.append(Edge(name, parent, path, line))
            if target in mods and target != name and (explicit or target not in enclosing):
                edges.append(Edge(name, target, path, line, names))

        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    add(alias.name, node.lineno, explicit=False)
            elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
                  and isinstance(node.args[0].value, str) and not node.args[0].value.startswith(".")
                  and (node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", ""))
                  == "import_module"):
                add(node.args[0].value, node.lineno, explicit=False)  # importlib.import_module("archive.x")
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(node, name, path)
                if not (target == "archive" or target.startswith("archive.")):
                    continue
                names = tuple(alias.name for alias in node.names)
                attributes = tuple(n for n in names if f"{target}.{n}" not in mods)
                for n in names:
                    if f"{target}.{n}" in mods:
                        add(f"{target}.{n}", node.lineno, (), explicit=False)
                if attributes:
                    add(target, node.lineno, attributes)
                else:  # ``from pkg import submodule``: pkg is started, not needed whole
                    add(target, node.lineno, (), explicit=False)
    return edges


def find_cycles(edges: list[Edge]) -> list[list[Edge]]:
    """One cycle (as its edges, in order) per strongly connected component with a cycle."""
    graph: dict[str, list[Edge]] = {}
    for e in edges:
        graph.setdefault(e.source, []).append(e)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def strongconnect(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for e in graph.get(v, []):
            if e.target not in index:
                strongconnect(e.target)
                low[v] = min(low[v], low[e.target])
            elif e.target in on_stack:
                low[v] = min(low[v], index[e.target])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    cycles = []
    for component in components:
        start = min(component)
        # breadth-first from start back to start inside the component: a shortest cycle
        previous: dict[str, Edge] = {}
        frontier = [start]
        found = None
        while frontier and found is None:
            nxt = []
            for v in frontier:
                for e in graph.get(v, []):
                    if e.target not in component:
                        continue
                    if e.target == start:
                        found = e
                        break
                    if e.target not in previous:
                        previous[e.target] = e
                        nxt.append(e.target)
                if found is not None:
                    break
            frontier = nxt
        path = [found]
        while path[-1].source != start:
            path.append(previous[path[-1].source])
        cycles.append(path[::-1])
    return cycles


def _where(e: Edge) -> str:
    return f"{e.path.relative_to(ROOT)}:{e.line}"


def test_graph_of_the_package():
    """Every module parses; the package __init__ re-exporting its submodules is seen (DESIGN's
    sources package); edges stay inside archive and never loop on one module."""
    edges = import_edges()
    pairs = {(e.source, e.target) for e in edges}
    assert ("archive.sources", "archive.sources.raw") in pairs
    assert ("archive.sources.open", "archive.catalog.root") in pairs  # the one way from sources to the catalog
    assert not any(e.source == e.target for e in edges)
    assert all(e.source.startswith("archive") and e.target.startswith("archive") for e in edges)


def test_graph_rules_on_a_made_up_package(tmp_path):
    files = {
        "archive/__init__.py": "",
        "archive/p/__init__.py": "from archive.p.a import f\n",
        "archive/p/a.py": "from archive.p import g\n",          # needs p whole: a cycle with p's __init__
        "archive/p/b.py": "from . import a\n",                  # a submodule: p is only started
        "archive/q.py": "def f():\n    from .p import b\n",   # relative, inside a function
        "archive/r.py": "import archive.p.a as x\nfrom archive.q import _private, public\n",
        "archive/s.py": "import importlib\nM = importlib.import_module('archive.q')\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    mods = {".".join(Path(n).with_suffix("").parts[:-1] if n.endswith("__init__.py")
                     else Path(n).with_suffix("").parts): tmp_path / n for n in files}
    edges = import_edges(mods)
    assert {(e.source, e.target, e.names) for e in edges} == {
        ("archive.p", "archive.p.a", ("f",)), ("archive.p.a", "archive.p", ("g",)),
        ("archive.p.b", "archive.p.a", ()), ("archive.q", "archive.p", ()), ("archive.q", "archive.p.b", ()),
        ("archive.r", "archive.p", ()), ("archive.r", "archive.p.a", ()),
        ("archive.r", "archive.q", ("_private", "public")), ("archive.s", "archive.q", ())}
    (cycle,) = find_cycles(edges)
    assert {e.source for e in cycle} == {"archive.p", "archive.p.a"}


def test_cycle_finder_reports_the_path(tmp_path):
    a, b, c = (Edge("archive.a", "archive.b", tmp_path / "a.py", 1), Edge("archive.b", "archive.c", tmp_path / "b.py", 2),
               Edge("archive.c", "archive.a", tmp_path / "c.py", 3))
    (cycle,) = find_cycles([a, b, c, Edge("archive.a", "archive.d", tmp_path / "a.py", 4)])
    assert [e.source for e in cycle] == ["archive.a", "archive.b", "archive.c"]
    assert find_cycles([a, b]) == []


def test_no_import_cycles():
    cycles = find_cycles(import_edges())
    text = "\n".join(" -> ".join(f"{e.source} ({_where(e)})" for e in cycle) + f" -> {cycle[0].source}"
                     for cycle in cycles)
    assert not cycles, f"import cycles among archive modules:\n{text}"


def test_no_private_names_imported_across_modules():
    bad = [f"{_where(e)}: {e.source} imports {n} from {e.target}"
           for e in import_edges() for n in e.names
           if n.startswith("_") and not (n.startswith("__") and n.endswith("__"))]
    # ``import archive.x._y`` / ``from archive.x import _y`` where _y is a module: only from inside archive.x
    for e in import_edges():
        parts = e.target.split(".")
        for i, part in enumerate(parts):
            owner = ".".join(parts[:i])
            if (part.startswith("_") and not part.startswith("__")
                    and not (e.source == owner or e.source.startswith(owner + "."))):
                bad.append(f"{_where(e)}: {e.source} imports the private module {e.target}")
    assert not bad, "private names imported from another archive module:\n" + "\n".join(bad)


#: DESIGN 1's data flow as dependency layers, the depended-upon first: a module imports only modules of
#: its own layer and of the layers listed before it, never of one listed after it (no arrow runs back
#: up the data flow). Raw files are read by formats, turned into poses by the geometry, stored (the
#: collection store, the DEM it follows, its catalog), read back through sources; the GL renderer and the writers are
#: the stages the graph chains; the graph is driven by the commands (options -> pipeline -> cluster,
#: the library API, ingest, the viewer), and those by the command line.
LAYERS = [
    ("foundation", ("archive.errors", "archive.storage", "archive.files", "archive.codecs", "archive.overlap",
                    "archive.params", "archive.grid")),   # storage: where archives live (local paths, s3:// URLs)
    ("formats", ("archive.formats",)),
    ("geometry", ("archive.geometry",)),
    ("store", ("archive.collection",)),
    ("terrain", ("archive.terrain",)),   # a collection records the DEM it was ingested with
    ("catalog", ("archive.catalog",)),
    ("sources", ("archive.sources",)),
    ("render", ("archive.render",)),
    ("writers", ("archive.outputs",)),
    ("graph", ("archive.graph",)),
    ("drawing", ("archive.drawing",)),   # the viewer's drawing engine: a flight's tiles, planes, points, previews
    ("run", ("archive.run",)),   # options, the cluster, single renders, batches, tiles, stacks (one runner)
    ("features", ("archive.run.command", "archive.api", "archive.api_errors", "archive.ingest", "archive.simulator", "archive.view",
                  "archive.analysis",
                  "archive.calibrate", "archive.watch")),
    ("entry", ("archive.cli", "archive.__main__")),
]
#: Edges the layers allow that DESIGN 1 still forbids: (importer prefix, forbidden target prefixes, exempt
#: importers). "formats know nothing of sources, sources nothing of the catalog (only the open_source
#: function resolves an archive id), the catalog nothing of rendering"; "graph/ imports no concrete
#: writer" (only the sink interface, :mod:`archive.outputs.base`); "view/ no command module"; ingest nothing of
#: the viewer (its previews are drawn by drawing/).
FORBIDDEN = [
    ("archive.formats.", ("archive.",), ("archive.errors", "archive.files", "archive.formats.")),
    ("archive.sources.", ("archive.catalog",), ()),
    ("archive.graph", ("archive.outputs.",), ("archive.outputs.base",)),
    ("archive.view", ("archive.run.pipeline", "archive.cli", "archive.run.command", "archive.run.cluster"), ()),
    ("archive.ingest", ("archive.view",), ()),   # ingest draws its previews with drawing/, never through the viewer
]
#: The one module of sources/ that resolves collection ids through the archive (and the package
#: __init__ that re-exports it).
OPENS = ("archive.sources.open", "archive.sources")


def _layer(module: str) -> int | None:
    """Index in LAYERS of ``module`` by its longest listed prefix (the package ``archive`` itself: the top),
    None if unlisted."""
    if module == "archive":
        return len(LAYERS) - 1
    found = [(len(p), i) for i, (_, prefixes) in enumerate(LAYERS) for p in prefixes
             if module == p or module.startswith(p + ".")]
    return max(found)[1] if found else None   # the longest prefix: run.command is a feature over run/


def test_every_module_has_a_layer():
    unlisted = [m for m in modules() if _layer(m) is None]
    assert not unlisted, f"modules outside DESIGN 1's layers (add them to LAYERS): {unlisted}"


def test_dependencies_point_down():
    bad = []
    for e in import_edges():
        source, target = _layer(e.source), _layer(e.target)
        if source is not None and target is not None and target > source:
            bad.append(f"{_where(e)}: {e.source} ({LAYERS[source][0]}) imports {e.target} ({LAYERS[target][0]})")
        for prefix, forbidden, allowed in FORBIDDEN:
            if not (e.source == prefix or e.source.startswith(prefix)) or e.source in OPENS:
                continue
            if any(e.target.startswith(f) for f in forbidden) and not any(e.target.startswith(a) for a in allowed):
                bad.append(f"{_where(e)}: {e.source} imports {e.target}")
    assert not bad, "imports against the layering of DESIGN 1:\n" + "\n".join(bad)


def test_the_layer_rules_catch_what_they_should():
    """The rules on made-up edges: graph -> a concrete writer, view -> pipeline / the CLI, the catalog
    -> a source, formats -> navigation, sources -> the catalog are refused; graph -> the sink
    interface and sources.open -> the catalog pass."""
    def refused(source: str, target: str) -> bool:
        s, t = _layer(source), _layer(target)
        if s is not None and t is not None and t > s:
            return True
        return any((source == p or source.startswith(p)) and source not in OPENS
                   and any(target.startswith(f) for f in forbidden) and not any(target.startswith(a) for a in allowed)
                   for p, forbidden, allowed in FORBIDDEN)

    assert refused("archive.graph.build", "archive.outputs.cog")
    assert refused("archive.graph.lazy", "archive.outputs.zarr")
    assert not refused("archive.graph.build", "archive.outputs.base")
    assert refused("archive.drawing.flight", "archive.run.pipeline") and refused("archive.drawing.flight", "archive.view.registry")
    assert refused("archive.view.registry", "archive.run.pipeline") and refused("archive.view.server", "archive.cli")
    assert refused("archive.ingest.previews", "archive.view.registry")
    assert not refused("archive.ingest.previews", "archive.drawing.flight")
    assert refused("archive.catalog.index", "archive.sources.raw")
    assert refused("archive.formats.lcf", "archive.geometry.navigation")
    assert refused("archive.sources.raw", "archive.catalog.root")
    assert not refused("archive.sources.open", "archive.catalog.root")
    assert refused("archive.outputs.zarr", "archive.graph.plan") and refused("archive.sources.raw", "archive.render.mesh")


#: Private names of Dask and argparse a module must not use: their internals change without notice.
PRIVATE_OWNERS = ("dask", "distributed", "argparse")


def test_no_private_names_of_dask_or_argparse():
    """No ``dask._task_spec`` (``dask.task_spec`` is public), no ``parser._negative_number_matcher``,
    no ``argparse._SubParsersAction``: neither private modules of Dask nor private attributes."""
    bad = []
    for name, path in modules().items():
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                parts = node.module.split(".")
                if parts[0] in PRIVATE_OWNERS and any(p.startswith("_") for p in parts[1:]):
                    bad.append(f"{where}: from {node.module} import ...")
                if parts[0] in PRIVATE_OWNERS:
                    bad += [f"{where}: imports {a.name} from {node.module}" for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
            elif isinstance(node, ast.Import):
                bad += [f"{where}: import {a.name}" for a in node.names if a.name.split(".")[0] in PRIVATE_OWNERS
                        and any(p.startswith("_") for p in a.name.split(".")[1:])]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                root = node.value
                while isinstance(root, ast.Attribute):
                    root = root.value
                if (isinstance(root, ast.Name) and root.id in PRIVATE_OWNERS) or node.attr == "_negative_number_matcher":
                    bad.append(f"{where}: .{node.attr}")
    assert not bad, "private Dask / argparse names used:\n" + "\n".join(bad)


def test_only_render_imports_gl():
    """Statically, imports inside functions included: moderngl only under archive/render/."""
    bad = []
    for name, path in modules().items():
        if name.startswith("archive.render"):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = ([a.name for a in node.names] if isinstance(node, ast.Import)
                       else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            bad += [f"{path.relative_to(ROOT)}:{node.lineno}: imports {t}" for t in targets
                    if t.split(".")[0] in GL_MODULES]
    assert not bad, "\n".join(bad)


def test_graph_package_never_computes():
    """DESIGN 1: ``graph/`` builds Dask collections and never computes them: no ``.compute(...)``
    or ``.persist(...)`` call (``dask.compute`` included)."""
    bad = []
    for name, path in modules().items():
        if not name.startswith("archive.graph"):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("compute", "persist", "compute_chunk_sizes")):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.func.attr}(...)")
    assert not bad, "\n".join(bad)


def _private_definitions(tree: ast.AST) -> set[str]:
    """``_names`` a module defines: functions, classes, methods, module/class variables, ``self._x``."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            out.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            out.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            out.add(node.attr)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out.add(node.target.id)
    return {n for n in out if n.startswith("_") and not n.startswith("__")}


def _private_uses(tree: ast.AST) -> Iterator[tuple[str, int]]:
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            yield node.attr, node.lineno


def test_no_private_members_of_other_modules_used():
    """``obj._name`` where ``_name`` is defined by ANOTHER archive module and not by this one (e.g. a
    private method of a class of another module)."""
    trees = {name: ast.parse(path.read_text(), str(path)) for name, path in modules().items()}
    defined = {name: _private_definitions(tree) for name, tree in trees.items()}
    bad = []
    for name, tree in trees.items():
        for attr, line in _private_uses(tree):
            if attr in defined[name]:
                continue
            owners = sorted(m for m, names in defined.items() if attr in names and m != name)
            if owners:
                where = modules()[name].relative_to(ROOT)
                bad.append(f"{where}:{line}: {name} uses {attr} of {', '.join(owners)}")
    assert not bad, "private members of other archive modules used:\n" + "\n".join(bad)


LIGHT = ["archive", "archive.cli", "archive.ingest.command", "archive.sources",
         *sorted(m for m in modules() if m.startswith("archive.catalog."))]
GL_MODULES = ("moderngl", "glcontext")


def _loaded_gl(module: str) -> tuple[str, subprocess.CompletedProcess]:
    code = (f"import sys, importlib; importlib.import_module({module!r}); "
            f"print(','.join(m for m in {GL_MODULES!r} if m in sys.modules))")
    return module, subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                                  cwd=ROOT)


def test_light_modules_do_not_import_moderngl():
    """Each in a fresh interpreter: importing it leaves moderngl (and its GL backend) out of sys.modules."""
    assert "archive.catalog.root" in LIGHT
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(_loaded_gl, LIGHT))
    failed = [f"{m}: import failed: {done.stderr.strip().splitlines()[-1:]}" for m, done in results
              if done.returncode != 0]
    assert not failed, "\n".join(failed)
    heavy = [f"{m} imports {done.stdout.strip()}" for m, done in results if done.stdout.strip()]
    assert not heavy, "\n".join(heavy)


@pytest.mark.parametrize("module", ["archive.graph.build", "archive.graph.tasks", "archive.graph.plan",
                                    "archive.graph.nodes", "archive.graph.lazy"])
def test_graph_modules_import_without_gl(module):
    """The graph only builds: its modules reach GL inside task bodies, never at import."""
    _, done = _loaded_gl(module)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "", f"{module} imports {done.stdout.strip()}"


#: Where an overlap rule is tested by name (issue 31): a rule name compared (``== "nadir"``,
#: ``!= 'last'``, ``in ("last", ...)``), a name-keyed helper of the old rule module (``rule_key(``,
#: ``make_rule(``), or that module imported.
RULE_NAMES = ("last", "nadir", "mean")
_QUOTED = "[\"'](?:" + "|".join(RULE_NAMES) + ")[\"']"
BY_NAME = re.compile("|".join([
    rf"[=!]=\s*{_QUOTED}", rf"{_QUOTED}\s*[=!]=",                   # == "nadir", "last" != x
    rf"\bin\s*[(\[{{][^)\]}}]*{_QUOTED}",                            # in ("last", "nadir")
    r"\b(?:rule_key|make_rule)\(", r"archive\.graph\.mosaic\b", r"\bWINNER_RULES\b",
]))


def name_tests(text: str) -> list[tuple[int, str]]:
    """(line number, line) of each line of ``text`` (Python source) that tests an overlap rule by name."""
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if BY_NAME.search(line)]


def test_name_tests_are_found():
    """The check finds what it should on made-up lines (and leaves other comparisons alone)."""
    for line in ['if rule == "nadir":', "if overlap != 'last':", 'if "mean" == p.overlap:',
                 'if query.overlap in ("last", "nadir"):', "key = rule_key(p.overlap)",
                 "from archive.graph.mosaic import RULES"]:
        assert name_tests(line), line
    for line in ['if mode == "radiance":', 'rule = RULES["nadir"]', 'if layer != "view_zenith":',
                 'stats = {"mean": 1.0}', "if rule.key is not None:"]:
        assert not name_tests(line), line


def test_no_overlap_rule_is_tested_by_name():
    """Issue 31: the overlap rule is resolved once (:func:`archive.overlap.overlap_rule`) and passed as
    an object; outside ``archive/overlap.py`` no module compares a rule's name or asks a name-keyed
    helper (its needs, its fast paths and its viewer entry are the object's)."""
    bad = [f"{path.relative_to(ROOT)}:{n}: {line}" for name, path in modules().items() if name != "archive.overlap"
           for n, line in name_tests(path.read_text())]
    assert not bad, "overlap rules tested by name outside archive/overlap.py:\n" + "\n".join(bad)


#: The output formats' names and command-line words, and their suffixes (issue 31): known to
#: ``archive/outputs/`` only (:mod:`archive.outputs.registry`); everyone else asks a format object.
FORMAT_WORDS = ("zarr", "cog", "envi", "tif", "tiff", "hdr")
FORMAT_SUFFIXES = tuple(f".{w}" for w in ("zarr", "tif", "tiff", "hdr"))


def format_tables(text: str) -> list[tuple[int, str]]:
    """(line number, what) of each place in ``text`` (Python source) that keeps its own knowledge of
    the output formats: a format name compared (``fmt == "cog"``, ``format in ("zarr", "tif")``), or
    a collection literal (tuple, list, set, dict keys) holding two or more format words or suffixes."""
    found = []

    def words(node: ast.AST, table: tuple[str, ...]) -> list[str]:
        items = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", [])
        return [k.value for k in items if isinstance(k, ast.Constant) and isinstance(k.value, str)
                and k.value.lower() in table]

    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Compare):
            for side in (node.left, *node.comparators):
                if isinstance(side, ast.Constant) and isinstance(side.value, str) and side.value in FORMAT_WORDS:
                    found.append((node.lineno, f"compares the format name {side.value!r}"))
        if isinstance(node, ast.Tuple | ast.List | ast.Set | ast.Dict):
            for table in (FORMAT_WORDS, FORMAT_SUFFIXES):
                listed = words(node, table)
                if len(set(listed)) >= 2:
                    found.append((node.lineno, f"lists the formats {listed}"))
    return found


def test_format_tables_are_found():
    """The check finds what it should on made-up lines (and leaves other strings alone)."""
    for line in ['if fmt == "zarr": pass', "ok = format in ('zarr', 'tif', 'hdr')", 'FORMATS = ("zarr", "tif", "hdr")',
                 'SUFFIX = {".zarr": "zarr", ".tif": "cog"}', 'if p.suffix in (".tif", ".tiff"): pass',
                 'q.add_argument("--format", choices=["zarr", "tif", "hdr"])']:
        assert format_tables(line), line
    for line in ['store = root / f"{cid}.zarr"', 'if zarr_format == 2: pass', 'DATA = (".bil", ".bip", ".bsq")',
                 'hdr = path.with_name(path.name + ".hdr")', 'kinds = ("zarr", "png")']:
        assert not format_tables(line), line


def test_one_format_table():
    """Issue 31: each output format is one object of its module (:class:`archive.outputs.base.OutputFormat`),
    listed by :mod:`archive.outputs.registry`; outside ``archive/outputs/`` no module lists format names
    or suffixes or compares a format's name (the catalog, the batch render and the CLI ask the objects)."""
    bad = [f"{path.relative_to(ROOT)}:{n}: {what}" for name, path in modules().items()
           if not name.startswith("archive.outputs.") for n, what in format_tables(path.read_text())]
    assert not bad, "output formats known outside archive/outputs/:\n" + "\n".join(bad)


def envi_header_writers(text: str) -> list[int]:
    """Line numbers of ``text`` (Python source) that start an ENVI header of their own: a string
    ``"ENVI"`` alone in a list or tuple (the header's first line), or a string starting ``"ENVI\\n"``."""
    lines = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.List | ast.Tuple):
            lines += [e.lineno for e in node.elts if isinstance(e, ast.Constant) and e.value == "ENVI"]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("ENVI\n"):
            lines.append(node.lineno)
        elif isinstance(node, ast.JoinedStr) and node.values and isinstance(node.values[0], ast.Constant) \
                and str(node.values[0].value).startswith("ENVI\n"):
            lines.append(node.lineno)
    return lines


def test_one_envi_header_writer():
    """Issue 31: the ENVI header is written one way, :func:`archive.formats.envi.header_text` (raw cubes
    written by :func:`~archive.formats.envi.write_envi`, rendered ENVI outputs, the simulator's Resonon
    headers); no other module starts a header of its own."""
    for line in ['rows = ["ENVI", "samples = 3"]', 'text = "ENVI\\nsamples = 3\\n"', 'text = f"ENVI\\nbands = {n}"']:
        assert envi_header_writers(line), line
    assert not envi_header_writers('if first.strip() != "ENVI": pass')
    writers = {name for name, path in modules().items() if envi_header_writers(path.read_text())}
    assert writers == {"archive.formats.envi"}, f"ENVI headers written outside archive.formats.envi: {writers}"


def given_fovs(text: str) -> list[int]:
    """Lines of ``text`` that give :class:`~archive.params.NavigationParams` a field of view (a
    ``fov_deg`` keyword, or anything positional: its fields are keywords)."""
    bad = []
    for node in ast.walk(ast.parse(text)):
        if not (isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None))
                == "NavigationParams"):
            continue
        if node.args or any(k.arg == "fov_deg" for k in node.keywords):
            bad.append(node.lineno)
    return bad


def test_no_dummy_field_of_view():
    """Issue 31: navigation parameters carry no field of view (poses do not depend on it); a source is
    opened with ``NavigationParams(sync_offset=...)`` and the field of view is the render's
    :class:`~archive.params.MeshSpec`'s (--fov, else the collections' record), decided once."""
    from dataclasses import fields

    from archive.params import NavigationParams

    assert "fov_deg" not in {f.name for f in fields(NavigationParams)}
    for line in ["NavigationParams(fov_deg=47.5)", "p.NavigationParams(fov_deg=fov or 47.5, sync_offset=None)",
                 "NavigationParams(47.5 if f is None else f)", "NavigationParams(fov_deg=fov, sync_offset=0.0)"]:
        assert given_fovs(line), line
    assert not given_fovs("NavigationParams(sync_offset=0.5)")
    files = [*modules().values(), *sorted((ROOT / "tests").glob("*.py")), *sorted((ROOT / "bench").glob("*.py"))]
    bad = [f"{path.relative_to(ROOT)}:{n}" for path in files for n in given_fovs(path.read_text())]
    assert not bad, "NavigationParams given a field of view:\n" + "\n".join(bad)


def test_one_mesh_spec():
    """Issue 31 item 2: the field of view, the ground (flat height or DEM), the view-angle limit and the
    output CRS of the meshes are one :class:`~archive.params.MeshSpec`, decided once in
    ``pipeline.open_inputs`` and passed whole: the records between the options and the graph hold no
    copy of them, and the render plan's mesh tasks take the MeshSpec itself."""
    from dataclasses import fields

    import archive.graph.plan as graph_plan
    from archive.params import MeshSpec, NavigationParams, RenderParams
    from archive.run.pipeline import Inputs, OutputPlan
    from archive.geometry.provenance import ProvenanceSpec

    copies = {"fov", "fov_deg", "ground_height", "grounds", "max_view_angle", "dem", "crs", "epsg"}
    for record in (NavigationParams, RenderParams, Inputs, OutputPlan, graph_plan.RenderPlan):
        held = {f.name for f in fields(record)} & copies
        assert not held, f"{record.__name__} holds its own {sorted(held)}: they are the MeshSpec's"
    assert {f.name for f in fields(MeshSpec)} == {"fov_deg", "ground_height", "max_view_angle", "epsg", "dem", "gsd"}
    assert {f.type for f in fields(Inputs) if f.name == "mesh_specs"} == {"tuple[MeshSpec, ...]"}
    assert {f.type for f in fields(OutputPlan) if f.name == "mesh_spec"} == {"MeshSpec"}
    assert {f.type for f in fields(graph_plan.RenderPlan) if f.name == "mesh_spec"} == {"MeshSpec | None"}
    assert not hasattr(graph_plan, "MeshParams")
    # the provenance layers take the ground from a MeshSpec too (one ground, not one per source)
    assert "grounds" not in {f.name for f in fields(ProvenanceSpec)}


def test_no_module_over_600_lines():
    """The house's cap (issue 44): a module that grows past 600 lines is split along its seams."""
    long = {str(p.relative_to(ROOT)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 600}
    assert not long, long
