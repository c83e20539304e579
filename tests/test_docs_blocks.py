"""Quick checks of the README's and the documentation pages' code blocks (``tests/docblocks.py``).

The blocks themselves run in ``tests/test_readme_run.py`` (marker ``readme``, minutes). These
checks take a second and catch what makes a block rot: a block the runner would not know how to
run, a renamed ``hs.NAME`` or a moved module in an example, and a command-line reference page
(``docs/cli.md``) that no longer matches the parser.
"""

from __future__ import annotations

import importlib
import re

import pytest

import hybridslam as hs

from .docblocks import PAGES, ROOT, all_blocks, blocks, commands, kind
from .scripts import load_script

CODE = [b for b in all_blocks() if b.lang in ("python", "bash")]


def test_every_page_is_listed():
    """A new documentation page joins the runner's list (and so the tests) or this fails."""
    on_disk = {p for p in (ROOT / "docs").rglob("*.md")}
    assert on_disk == set(PAGES[1:]), f"pages not in tests/docblocks.py PAGES: {sorted(on_disk - set(PAGES))}"
    assert len(CODE) >= 20, len(CODE)


@pytest.mark.parametrize("block", CODE, ids=lambda b: b.name)
def test_block_is_runnable_or_marked(block):
    """Each block is run by the readme suite, or says with ``<!-- skip-test: REASON -->`` why not."""
    if block.skip is not None:
        assert block.skip, f"{block.name}: a skip-test marker needs a reason"
        pytest.skip(f"{block.name}: {block.skip}")
    if block.lang == "python":
        compile(block.code, block.name, "exec")
    else:
        unknown = [c for c in commands(block) if kind(c) == "unknown"]
        assert not unknown, f"{block.name}: lines the runner cannot run (mark the block skip-test): {unknown}"


def _dotted(path: str) -> object:
    """``hybridslam.a.b.C`` imported: the longest module prefix, then attributes."""
    parts = path.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for name in parts[i:]:
            obj = getattr(obj, name)
        return obj
    raise ModuleNotFoundError(path)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_names_in_a_page_exist(page):
    """Every ``hs.NAME`` a page names (in its blocks or its text) and every ``from hybridslam... import``
    of its Python blocks exists: a renamed function breaks this test, not a reader."""
    text = page.read_text(encoding="utf-8")
    missing = sorted({n for n in re.findall(r"\bhs\.([A-Za-z_]\w*)", text) if not hasattr(hs, n)})
    assert not missing, f"{page.name}: hs.{missing} do not exist"
    for block in blocks(page):
        if block.lang != "python" or block.skip is not None:
            continue
        for module, names in re.findall(r"^\s*from (hybridslam[\w.]*) import ([\w, ]+)", block.code, flags=re.M):
            for name in (n.strip() for n in names.split(",")):
                assert hasattr(_dotted(module), name), f"{block.name}: from {module} import {name}"


def test_cli_page_matches_the_parser():
    """docs/cli.md is generated from the parser; rerun ``python3 scripts/cli_reference.py`` after a change."""
    script = load_script("scripts/cli_reference.py", "cli_reference")
    assert script.PAGE.read_text(encoding="utf-8") == script.render(), \
        "docs/cli.md is out of date: run python3 scripts/cli_reference.py"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_a_page_turns_float64_on_before_it_computes(page):
    """Importing hybridslam changes no process-wide setting, so a page whose Python imports it calls
    ``hs.setup()`` in that first block (or the reader's estimators refuse to run in float32)."""
    first = next((b for b in blocks(page) if b.lang == "python" and "import hybridslam" in b.code), None)
    if first is not None:
        assert "hs.setup()" in first.code, f"{first.name}: call hs.setup() after importing hybridslam"
