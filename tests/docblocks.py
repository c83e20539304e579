"""The code blocks of the README and the documentation pages, as the tests run them.

A page's ```` ```python ```` and ```` ```bash ```` blocks are its examples. Every one of them is run by
``tests/test_readme_run.py``, ``tests/test_readme_python.py`` or the test file about the page's
subject (marker ``readme``; :data:`WITH_COMMANDS`, :data:`IN_TEST_FILES`) unless the line before it
is an HTML comment ``<!-- skip-test: REASON -->`` (a block that needs a GPU, SLURM or several hosts);
the quick tests of ``tests/test_docs_blocks.py`` check that every block is one the runner knows how
to run, that each skipped one says why, and that the names and options the blocks use exist.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"



def _nav_pages() -> list[Path]:
    """The site's pages in ``mkdocs.yml``'s navigation order (every ``- [Title: ]page.md`` line of its
    ``nav:``): a page joins the site, and with it these tests, by one line there."""
    text = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    nav = re.search(r"^nav:\n(?P<body>(?:[ \t]+.*\n|\n)*)", text, re.M)
    assert nav, "mkdocs.yml has no nav:"
    return [ROOT / "docs" / m.strip("\"' ") for m in re.findall(r"^\s*-\s*(?:.*?:\s*)?(\S+\.md)\s*$", nav["body"], re.M)]


# The order the runner takes the pages in: the README first, then the site's navigation order, so
# that a page's commands find the files an earlier page wrote (logs/ from the MRCLAM imports).
PAGES = [README] + _nav_pages()

_FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.M | re.S)
_SKIP = re.compile(r"<!--\s*skip-test:\s*(?P<reason>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    skip: str | None  # the reason of a preceding <!-- skip-test: ... -->, or None

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """Every fenced block of a page, in order (indented ones in lists included)."""
    text = page.read_text(encoding="utf-8")
    out = []
    for m in _FENCE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        skip = _SKIP.search(before)
        indent = m.group("indent")
        code = "\n".join(s[len(indent):] if s.startswith(indent) else s for s in m.group("body").split("\n"))
        out.append(Block(page, line, m.group("lang"), code, skip.group("reason") if skip else None))
    return out


def all_blocks(lang: str | None = None) -> list[Block]:
    return [b for p in PAGES for b in blocks(p) if lang is None or b.lang == lang]


def command_lines(block: Block) -> list[str]:
    """A bash block's command lines (continuations joined, comments dropped)."""
    lines = []
    for line in re.sub(r"\\\n\s*", " ", block.code).splitlines():
        line = line.split("  #")[0].strip()
        if line and not line.startswith("#"):
            lines.append(line)
    return lines


def is_synopsis(command: str) -> bool:
    """``hybridslam sweep [-o runs/sweep] [--alphas ...]``: a usage line, parsed but not run."""
    return "[" in command


def kind(command: str) -> str:
    """What the runner does with one ``&&``-separated command: ``run`` (a hybridslam command),
    ``script`` (an experiments/ or scripts/ line, checked against its --help), ``ci`` (install, test,
    docs build: what CI runs itself) or ``unknown`` (a test failure: mark its block skip-test)."""
    if command.startswith("hybridslam "):
        return "synopsis" if is_synopsis(command) else "run"
    if re.match(r"python3 (experiments|scripts)/", command):
        return "script"
    if re.match(r"(python3 -m (pip|pytest|mypy)\b|mkdocs )", command):
        return "ci"
    return "unknown"


def commands(block: Block) -> list[str]:
    return [part.strip() for line in command_lines(block) for part in line.split("&&")]


def runnable(page: Path) -> list[str]:
    """The page's commands that the runner runs or checks (kinds ``run`` and ``script``), in order."""
    return [c for b in blocks(page) if b.lang == "bash" and b.skip is None for c in commands(b)
            if kind(c) in ("run", "script")]


def python_blocks(page: Path) -> list[Block]:
    return [b for b in blocks(page) if b.lang == "python" and b.skip is None]


# The pages whose Python blocks run beside the commands (tests/test_readme_run.py, after them, in the
# commands' process): those with commands (their Python reads the files the commands write) and
# those whose Python builds a program a command builds alike (the API page's and the file-format
# page's runs are the README's `hybridslam run`s), so that it is traced and compiled once. Every other
# page's Python runs in tests/test_readme_python.py (the two files run side by side on CI's two
# workers) or in the test file about its subject (IN_TEST_FILES, below).
SHARES_PROGRAMS = ("index.md", "api.md", "file_format.md")
WITH_COMMANDS = [p for p in PAGES if runnable(p) or p.name in SHARES_PROGRAMS]

# The pages whose Python runs in the process of the test file about their subject (:func:`run_here`),
# because the page and that file's tests build the same programs: in one process JAX traces and
# compiles each once (its in-memory caches are per process, and a program with a host callback, as
# the planner's refinement, never reaches the persistent compilation cache). Each file has one test,
# marked ``readme``, that calls ``run_here(request, PAGE)``; tests/test_readme_python.py checks that
# this table is what the files call, and runs every other page's Python.
IN_TEST_FILES = {"planning.md": "test_planning.py"}


def run_here(request, page: str) -> dict:
    """Run ``docs/PAGE``'s Python blocks in this process, as the worker runs a page
    (``tests/docworker.py``'s ``run_blocks``): in order, in one fresh namespace, what they print
    captured, in the test's ``tmp_path``, starting in float32 (the page turns float64 on itself:
    ``hs.setup()``; the suite's float64 is restored after). A failure names the block and its line
    (``File "docs/planning.md", line 23``). The rest of the configuration is the suite's: rank
    promotion raises (a part of JAX's cache keys: the page's programs are the tests') and the type
    checker runs. Returns the namespace the blocks leave (``ns["plan"]``). ``request``: the calling
    test's, which must be marked ``readme`` and be in the file :data:`IN_TEST_FILES` names."""
    import jax

    from .docworker import run_blocks

    path = ROOT / "docs" / page
    assert IN_TEST_FILES.get(page) == request.path.name, f"{page} is not {request.path.name}'s: IN_TEST_FILES"
    assert request.node.get_closest_marker("readme"), f"{request.node.nodeid} runs {page}: mark it readme"
    monkeypatch = request.getfixturevalue("monkeypatch")
    monkeypatch.chdir(request.getfixturevalue("tmp_path"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    x64 = jax.config.read("jax_enable_x64")
    try:
        namespace, answer = run_blocks([[b.name, b.line, b.code] for b in python_blocks(path)])
    finally:
        jax.config.update("jax_enable_x64", x64)
    failed = answer["failed"]
    assert failed is None, f"{failed} failed:\n{answer['error']}\n{answer['output'][-3000:]}"
    return namespace


def run_here_calls(test_file: Path) -> list[str]:
    """The pages a test file runs with :func:`run_here` (its calls' literal page names)."""
    text = test_file.read_text(encoding="utf-8")
    return re.findall(r"\brun_here\(\s*request\s*,\s*[\"']([^\"']+)[\"']", text)
