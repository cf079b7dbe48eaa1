"""The README and docs/ as a user meets them (issue 49 item 5, issue 44 point 5).

- Every shell and Python block of README.md and of the docs pages listed in :data:`MARKED_PAGES` says whether it runs:
  ``<!-- run -->``, ``<!-- run: slow -->`` or ``<!-- no-run: why -->`` on the line before the fence.
- README.md's ``run`` blocks run in order, as written, in one empty folder, with the installed ``archive``
  (about 30 s on a 2-core machine). Each docs page's ``run`` blocks run the same way in a folder of their own
  when ``ARCHIVE_DOCS_RUN=1`` (about 100 s more; ``run: slow`` blocks, minutes, also need
  ``ARCHIVE_DOCS_RUN=slow``).
- No two examples make the same folder or output (the co-registration example once failed with "output
  exists already" because the stack example had made its folders).
- Every option of every command (read from ``archive <command> --help``, archive/cli.py's parser) is in its command's section of
  docs/commands.md (or on the command's own page, docs/<command>.md).
- Every "DESIGN n" the code cites is a section n of docs/design.md; every relative link resolves.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from archive.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"

#: Pages whose every shell block must carry a run marker (the pages this documentation keeps; the other
#: pages of docs/ may opt in by marking blocks, and their ``run`` blocks are run then).
MARKED_PAGES = ("README.md", "docs/archive.md", "docs/batch.md", "docs/calibration.md", "docs/cluster.md",
                "docs/commands.md", "docs/install.md", "docs/navigation.md", "docs/outputs.md",
                "docs/reflectance.md", "docs/render.md", "docs/stacks.md", "docs/view.md", "docs/stac-api.md",
                "docs/python.md", "docs/reliability.md", "docs/numbering.md", "docs/modules.md", "docs/design.md")

#: Pages other people are writing this very turn, which links may name before they exist.
PAGES_BEING_WRITTEN = {"docs/stats.md", "docs/watch.md", "docs/viewer.md", "docs/ecosystem.md", "docs/ingest.md"}

FENCE = re.compile(r"^```(\w*)\s*$")
MARKER = re.compile(r"^<!--\s*(run|run:\s*slow|no-run:.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    """A fenced shell or Python block of a page: its text, the line its fence opens on (1-based), its
    marker (``run``, ``slow``, ``no-run`` or None) and its language (``sh`` or ``python``)."""
    page: str
    line: int
    text: str
    marker: str | None
    language: str = "sh"


def shell_blocks(path: Path, languages: tuple[str, ...] = ("sh",)) -> list[Block]:
    """The ```sh / ```bash / ```shell blocks of a Markdown page (and its ```python blocks when
    ``languages`` has "python"), in order, each with its marker."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    page = str(path.relative_to(ROOT))
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        language = "sh" if m.group(1) in ("sh", "bash", "shell") else m.group(1)
        if language in languages:
            before = next((lines[k] for k in range(i - 1, -1, -1) if lines[k].strip()), "")
            mk = MARKER.match(before.strip())
            marker = None if mk is None else ("slow" if mk.group(1).replace(" ", "") == "run:slow"
                                              else "run" if mk.group(1) == "run" else "no-run")
            blocks.append(Block(page, i + 1, "\n".join(lines[i + 1:j]), marker, language))
        i = j + 1
    return blocks


def pages() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def commands(block: Block) -> list[list[str]]:
    """The ``archive ...`` command lines of a block, continuation lines joined, comments and shell
    loops' words around them dropped, split as the shell would (variables kept as written)."""
    text = re.sub(r"\\\n\s*", " ", block.text)
    out = []
    for raw in text.splitlines():
        for part in re.split(r";|\|\||&&|\|", raw):
            try:
                words = shlex.split(part, comments=True)
            except ValueError:
                continue
            while words and words[0] in ("do", "then", "for", "done", "time"):
                words = words[1:] if words[0] != "for" else []
            if len(words) > 1 and words[0] == "archive":
                out.append(words[1:])
    return out


def _archive_bin() -> str:
    here = Path(sys.executable).parent / "archive"
    found = str(here) if here.exists() else shutil.which("archive")
    if found is None:
        pytest.skip("no installed 'archive' command (pip install -e . first)")
    return found


def run_blocks(blocks: list[Block], folder: Path, timeout: float = 600) -> list[str]:
    """Run each block with bash (``set -e``) in ``folder``, in order, the installed ``archive`` first on
    PATH; the output of each. A failing block fails the test naming the page, the line and the output."""
    env = dict(os.environ, PATH=f"{Path(_archive_bin()).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    outputs = []
    for b in blocks:
        # python -c, not a file: the local cluster's spawned workers do not run the example again
        argv = [sys.executable, "-c", b.text] if b.language == "python" else ["bash", "-e", "-c", b.text]
        proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True,
                              timeout=timeout)
        if proc.returncode != 0:
            pytest.fail(f"{b.page}, the block at line {b.line} exits {proc.returncode} in {folder}:\n{b.text}\n"
                        f"--- its output (end) ---\n{(proc.stdout + proc.stderr)[-4000:]}")
        outputs.append(proc.stdout + proc.stderr)
    return outputs


# -- the markers ----------------------------------------------------------------------------------------

def test_every_shell_block_of_the_kept_pages_is_marked():
    unmarked = [f"{b.page}:{b.line}" for p in MARKED_PAGES if (ROOT / p).exists()
                for b in shell_blocks(ROOT / p, ("sh", "python")) if b.marker is None]
    assert not unmarked, ("shell blocks without <!-- run -->, <!-- run: slow --> or <!-- no-run: why --> on "
                          f"the line before: {unmarked}")


def test_the_front_page_is_short_and_names_the_two_jobs_of_dev_sh():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    first = shell_blocks(README)[0]
    assert [ln.split("#")[0].strip() for ln in first.text.splitlines()] == ["./dev.sh demo", "./dev.sh test"]
    dev = (ROOT / "dev.sh").read_text(encoding="utf-8")
    assert re.search(r"^\s+demo\)$", dev, re.M) and re.search(r"^\s+test\)$", dev, re.M)
    ci = [ln for ln in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
          if ln.strip() and not ln.startswith("#")]
    assert ci[-1].strip() == "exec ./dev.sh test", ".ci/run must run exactly the README's test command"


# -- running them ---------------------------------------------------------------------------------------

def test_the_readme_blocks_run_in_order_in_an_empty_folder(tmp_path):
    blocks = [b for b in shell_blocks(README) if b.marker == "run"]
    assert len(blocks) >= 8, "the README's command examples are marked <!-- run -->"
    outputs = run_blocks(blocks, tmp_path)
    demo = tmp_path / "demo"
    for made in ("flight/truth", "mosaic.tif", "mosaic.tif.json", "mosaic_provenance.tif", "quicklook.png",
                 "from-archive.zarr.json", "batch/report.json", "stack.zarr.json"):
        assert (demo / made).exists(), f"the README's examples did not make demo/{made}"
    # one name per flight: the id `archive info` prints is the collection `archive ingest` made
    info = next(o for b, o in zip(blocks, outputs) if "archive info" in b.text)
    cid = re.search(r"\(id ([^)]+)\)", info).group(1)
    assert (demo / "archive" / "collections" / f"{cid}.zarr").is_dir(), (cid, info)
    assert cid in next(o for b, o in zip(blocks, outputs) if "catalog search" in b.text)


def _docs_pages_with_run_blocks() -> list[str]:
    return [str(p.relative_to(ROOT)) for p in sorted(DOCS.glob("*.md"))
            if any(b.marker in ("run", "slow") for b in shell_blocks(p, ("sh", "python")))]


@pytest.mark.slow
@pytest.mark.parametrize("page", _docs_pages_with_run_blocks())
def test_the_docs_blocks_run_in_order(page, tmp_path):
    wanted = os.environ.get("ARCHIVE_DOCS_RUN", "")
    if wanted not in ("1", "slow"):
        pytest.skip("docs pages' examples run with ARCHIVE_DOCS_RUN=1 (about 100 s; =slow: also the minutes-long ones)")
    markers = ("run", "slow") if wanted == "slow" else ("run",)
    blocks = [b for b in shell_blocks(ROOT / page, ("sh", "python")) if b.marker in markers]
    if not blocks:
        pytest.skip(f"{page} has only slow blocks (ARCHIVE_DOCS_RUN=slow)")
    run_blocks(blocks, tmp_path)


def _made_by(words: list[str]) -> list[str]:
    """What an ``archive`` command line creates and would refuse to make again: the folder of
    ``simulate``, the ``--out`` of ``render`` (unless --overwrite or --resume says it may exist)."""
    if words[0] == "simulate" and "--overwrite" not in words:
        return [w for w in words[1:2] if not w.startswith("-")]
    if words[0] == "render" and "--out" in words and not {"--overwrite", "--resume"} & set(words):
        return [words[words.index("--out") + 1]]
    return []


def test_no_two_examples_make_the_same_folder():
    seen: dict[str, str] = {}
    clashes = []
    for path in pages():
        for b in shell_blocks(path):
            if b.marker not in ("run", "slow"):    # servers, clusters, S3: not run, may reuse names
                continue
            for words in commands(b):
                for made in _made_by(words):
                    where = f"{b.page}:{b.line}"
                    if made in seen:
                        clashes.append(f"{made}: {seen[made]} and {where}")
                    seen.setdefault(made, where)
    assert not clashes, "examples that make the same path (run in one folder, the second fails): " + "; ".join(clashes)


def test_the_clash_finder_sees_a_clash():
    """The check above would have caught issue 49's co-registration example (demo/day1 twice)."""
    b = Block("x.md", 1, "archive simulate demo/day1 --seed 1 --quiet\narchive simulate demo/day1 \\\n  --cubes 4", "run")
    assert [m for w in commands(b) for m in _made_by(w)] == ["demo/day1", "demo/day1"]
    loop = Block("x.md", 1, "for k in 0 1; do archive simulate demo/raw$k --quiet; done", "run")
    assert [m for w in commands(loop) for m in _made_by(w)] == ["demo/raw$k"]


# -- every option documented ------------------------------------------------------------------------------

def _help(words: tuple[str, ...]) -> str:
    """``archive WORDS --help`` as the user reads it (the parser of archive/cli.py, in-process)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        build_parser().parse_args([*words, "--help"])
    return out.getvalue()


def _subcommands(words: tuple[str, ...] = ()):
    """(name, options) of every command and sub-command, read from their ``--help`` (public argparse
    output, no parser internals): ('archive catalog search', {'--archive', '--bbox', ...}), ..."""
    text = _help(words)
    for sub in re.findall(r"^ {4}([a-z][\w-]*)(?= {2,}|$)", text, re.M):   # a COMMAND / SUBCOMMAND list
        sub_help = _help((*words, sub))
        options = set(re.findall(r"^ {2}(?:-\w[^,\n]*, )?(--[\w-]+)", sub_help, re.M)) - {"--help"}
        yield " ".join(("archive", *words, sub)), options
        yield from _subcommands((*words, sub))


def _section(text: str, heading: str) -> str:
    m = re.search(rf"^## {re.escape(heading)}\s*$(.*?)(?=^## |\Z)", text, re.M | re.S)
    return "" if m is None else m.group(1)


def test_every_option_of_every_command_is_in_the_docs():
    reference = (DOCS / "commands.md").read_text(encoding="utf-8")
    missing = []
    commands = dict(_subcommands())
    assert {"archive render", "archive simulate", "archive catalog search"} <= set(commands)
    assert {"--cubes-per-pass", "--scene-seed"} <= commands["archive simulate"]   # the help was read
    for name, options in commands.items():
        top = " ".join(name.split()[:2])          # 'archive catalog search' is in '## archive catalog'
        own = DOCS / f"{name.split()[1]}.md"
        text = _section(reference, top) + (own.read_text(encoding="utf-8") if own.exists() else "")
        if not text:
            missing.append(f"{name} (no '## {top}' in docs/commands.md)")
            continue
        missing += [f"{name} {opt}" for opt in sorted(options)
                    if not re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", text)]
    assert not missing, "options not in their command's section of docs/commands.md: " + ", ".join(missing)


def test_the_synopses_name_only_options_that_exist():
    """The reverse: an option in a synopsis of docs/commands.md that its command no longer has."""
    reference = (DOCS / "commands.md").read_text(encoding="utf-8")
    options: dict[str, set[str]] = {}
    for name, known in _subcommands():
        top = " ".join(name.split()[:2])
        options.setdefault(top, set()).update(known)
    stale = []
    for top, known in options.items():
        for synopsis in re.findall(r"^```\n(.*?)^```", _section(reference, top), re.M | re.S):
            stale += [f"{top} {o}" for o in re.findall(r"(?<![\w-])--[a-z0-9]+(?:-[a-z0-9]+)*", synopsis)
                      if o not in known]
    assert not stale, f"docs/commands.md names options its commands do not have: {stale}"


# -- the design and the links -----------------------------------------------------------------------------

def test_every_design_section_the_code_cites_is_in_docs_design():
    sections = set(re.findall(r"^## (\d+)\. ", (DOCS / "design.md").read_text(encoding="utf-8"), re.M))
    cited: dict[str, str] = {}
    for folder in ("archive", "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for n in re.findall(r"\bDESIGN (\d+)\b", path.read_text(encoding="utf-8")):
                cited.setdefault(n, str(path.relative_to(ROOT)))
    assert len(cited) >= 8, cited          # the code cites sections 1-12: the search found them
    assert not {n: f for n, f in cited.items() if n not in sections}, f"cited, not in docs/design.md: {cited}"
    assert sections == {str(n) for n in range(1, len(sections) + 1)}, "sections numbered 1, 2, ... n"


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def test_relative_links_resolve():
    broken = []
    for path in pages():
        for target in LINK.findall(path.read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target) or target.startswith("#"):
                continue
            file = (path.parent / target.split("#")[0]).resolve()
            name = str(file.relative_to(ROOT)) if file.is_relative_to(ROOT) else str(file)
            if not file.exists() and name not in PAGES_BEING_WRITTEN:
                broken.append(f"{path.relative_to(ROOT)} -> {target}")
    assert not broken, broken
