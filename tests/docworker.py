"""The process that runs the documentation pages' Python blocks for ``tests/test_readme_run.py``.

One process for every page, so that the imports and JAX's compiles are shared: a program that two
pages build alike (the README's and the home page's run) compiles once. Each request is one JSON
line on stdin, ``{"page": NAME, "blocks": [[BLOCK_NAME, LINE, CODE], ...]}``; the page's blocks run
in order in one fresh namespace (as one script would), each compiled under the page's file name with
its lines where the page has them, so a traceback reads ``File "docs/planning.md", line 23``. The
answer is one JSON line on the original stdout: ``{"failed": BLOCK_NAME or null, "error": TRACEBACK,
"output": what the blocks printed}``. Run as ``python3 tests/docworker.py WORKDIR``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
import traceback


def run_page(blocks: list[list]) -> dict:
    namespace: dict = {"__name__": "__main__"}
    output = io.StringIO()
    failed, error = None, ""
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        for name, line, code in blocks:
            path = name.rsplit(":", 1)[0]
            try:
                exec(compile("\n" * line + code, path, "exec"), namespace)  # noqa: S102 - the page is the test
            except BaseException:  # noqa: BLE001 - a block's SystemExit is its failure too
                failed, error = name, traceback.format_exc()
                break
    if "matplotlib.pyplot" in sys.modules:  # a page's figures are not the next page's
        sys.modules["matplotlib.pyplot"].close("all")
    return {"failed": failed, "error": error, "output": output.getvalue()}


def main() -> None:
    os.chdir(sys.argv[1])
    sys.path.insert(0, os.getcwd())  # as `python3 script.py` in the folder would
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # what is printed outside a page (by Python or by XLA) goes to stderr, not the answers
    for request in sys.stdin:
        answer = run_page(json.loads(request)["blocks"])
        answers.write(json.dumps(answer) + "\n")
        answers.flush()


if __name__ == "__main__":
    main()
