"""The viewer page's ES modules (``archive/view/static/*.js``) read as the browser reads them: every
static import names a module that exists, and no modules import each other in a circle (issue 44 point
4). The import graph is read from the source (``import ... from "./x.js"``, ``import "./x.js"``,
``export ... from "./x.js"``); dynamic ``import()`` is not a static edge."""

from __future__ import annotations

import re
from pathlib import Path

STATIC = Path(__file__).resolve().parents[1] / "archive" / "view" / "static"
#: A static import or re-export of a module of the page: ``import {a} from "./m.js"``, ``import "./m.js"``,
#: ``export {a} from "./m.js"`` (over several lines too).
IMPORT = re.compile(r"""^\s*(?:import|export)\b(?:[^;"'()]*?\bfrom\s*)?\s*["'](\.{1,2}/[^"']+)["']""", re.M | re.S)


def module_imports(folder: Path = STATIC) -> dict[str, list[str]]:
    """{module file name: the page modules it imports statically, by file name}; the files of sub-folders
    (the vendored libraries, ``vendor/uplot/uPlot.esm.js``) by their path under ``folder``."""
    graph = {}
    for path in sorted(folder.rglob("*.js")):
        text = re.sub(r"//[^\n]*|/\*.*?\*/", "", path.read_text(encoding="utf-8"), flags=re.S)
        graph[path.relative_to(folder).as_posix()] = [
            (path.parent / target).resolve().relative_to(folder.resolve()).as_posix() for target in IMPORT.findall(text)]
    return graph


def import_cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """Every elementary cycle's modules (each once, the smallest name first), by depth-first search."""
    found: set[tuple[str, ...]] = set()

    def walk(start: str, node: str, path: list[str]) -> None:
        for nxt in graph.get(node, []):
            if nxt == start:
                i = path.index(min(path))
                found.add(tuple(path[i:] + path[:i]))
            elif nxt not in path and nxt > start:
                walk(start, nxt, path + [nxt])
    for start in sorted(graph):
        walk(start, start, [start])
    return [list(c) for c in sorted(found)]


def test_the_reader_sees_imports_and_cycles(tmp_path):
    (tmp_path / "a.js").write_text('import { b } from "./b.js";\n// import { z } from "./z.js";\nexport const a = 1;\n')
    (tmp_path / "b.js").write_text('import {\n  c,\n  d } from "./c.js";\nexport const b = 2;\n')
    (tmp_path / "c.js").write_text('import "./a.js";\nexport { x } from "./d.js";\nconst m = import("./a.js");\n')
    (tmp_path / "d.js").write_text("export const x = 3;\n")
    graph = module_imports(tmp_path)
    assert graph == {"a.js": ["b.js"], "b.js": ["c.js"], "c.js": ["a.js", "d.js"], "d.js": []}
    assert import_cycles(graph) == [["a.js", "b.js", "c.js"]]
    assert import_cycles({"a.js": ["b.js"], "b.js": []}) == []


def test_the_page_modules_import_no_circle_and_nothing_missing():
    graph = module_imports()
    assert {"app.js", "controls.js", "tiles.js", "spectra.js", "state.js", "params.js"} <= set(graph)
    missing = [f"{m} imports {t}" for m, targets in graph.items() for t in targets if t not in graph]
    assert not missing, missing
    cycles = import_cycles(graph)
    assert not cycles, "modules importing each other in a circle: " + "; ".join(" -> ".join(c + c[:1]) for c in cycles)
    # state.js is the bottom: it imports no module of the page
    assert graph["state.js"] == []


def test_every_module_the_page_loads_is_preloaded():
    """index.html names each module that app.js reaches by static imports in a ``modulepreload`` link, so
    the browser fetches them at once instead of one import level after the other (live.js was missed)."""
    graph = module_imports()
    reached, todo = set(), ["app.js"]
    while todo:
        for nxt in graph[todo.pop()]:
            if nxt not in reached:
                reached.add(nxt)
                todo.append(nxt)
    html = (STATIC / "index.html").read_text(encoding="utf-8")
    preloaded = set(re.findall(r'rel="modulepreload"\s+href="/static/([^"]+)"', html))
    vendored = {m for m in reached if "/" in m}   # a vendored library's own modules, if any
    assert reached - vendored - preloaded == set(), sorted(reached - vendored - preloaded)
