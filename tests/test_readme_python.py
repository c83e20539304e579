"""The Python blocks of the documentation pages that do not go with the commands
(``tests/docblocks.py``'s ``WITH_COMMANDS``: those run in ``tests/test_readme_run.py``) nor with the
tests of their subject (``IN_TEST_FILES``: ``docs/planning.md`` runs in ``tests/test_planning.py``'s
process, which builds the same programs), so that the files run side by side on CI's two workers.

Each page's blocks run in order as one script in a scratch folder of this file's own, each page in a
namespace of its own, all pages in one process (``tests/docworker.py``), so that the imports and
the compiles are shared; each page starts in float32, as a user's Python does, and turns float64 on
itself (``hs.setup()``). A failure names the page's block and line. A block after ``<!-- skip-test:
REASON -->`` is not run (``tests/test_docs_blocks.py`` reports it). Marked ``readme``, like
``tests/test_readme_run.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from .docblocks import IN_TEST_FILES, PAGES, ROOT, WITH_COMMANDS, python_blocks, run_here_calls
from .docworker import Worker

pytestmark = pytest.mark.readme

IN_TEST_PAGES = [ROOT / "docs" / name for name in IN_TEST_FILES]
PYTHON_PAGES = [p for p in PAGES if p not in WITH_COMMANDS and p not in IN_TEST_PAGES and python_blocks(p)]


def test_every_python_page_runs_in_exactly_one_test():
    """Each page with Python blocks is run by one test: with the commands (tests/test_readme_run.py),
    here, or by the one ``run_here`` call of the test file ``IN_TEST_FILES`` names for it."""
    calls = [(page, f.name) for f in sorted((ROOT / "tests").glob("test_*.py")) for page in run_here_calls(f)]
    assert sorted(calls) == sorted(IN_TEST_FILES.items())  # each listed page once, in its file; no other
    together = [p for p in WITH_COMMANDS if python_blocks(p)] + PYTHON_PAGES + IN_TEST_PAGES
    assert sorted(together) == sorted(p for p in PAGES if python_blocks(p))
    assert len(set(together)) == len(together)


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    worker = Worker(tmp_path_factory.mktemp("docs-python"))
    yield worker
    worker.close()


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_python_blocks_run(page: Path, worker: Worker):
    """A page's Python blocks, in order, as one script in the scratch folder; a failure names the
    block and its line in the page."""
    answer = worker.page(page, ROOT, python_blocks(page))
    assert answer["failed"] is None, f"{answer['failed']} failed:\n{answer['error']}\n{answer['output'][-3000:]}"
