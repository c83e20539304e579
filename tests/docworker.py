"""The process that runs the documentation pages' examples for ``tests/test_readme_run.py`` and
``tests/test_readme_python.py``, and the tests' side of it (:class:`Worker`).

One long-lived process per test file, so that the interpreter's start, the imports and JAX's
compiles are paid once: a program that two examples build alike (the README's ``hybridslam run
scenario.json`` and the API page's ``hs.run_estimator``) is traced and compiled once, however many
pages show it. Each request is one JSON line on stdin, each answer one JSON line on the original
stdout:

* ``{"page": NAME, "blocks": [[BLOCK_NAME, LINE, CODE], ...]}``: a page's Python blocks, in order,
  in one fresh namespace (as one script would), each compiled under the page's file name with its
  lines where the page has them, so a traceback reads ``File "docs/planning.md", line 23``. Each
  page starts in float32, as a user's Python does: the page turns float64 on itself (``hs.setup()``).
  Answer ``{"failed": BLOCK_NAME or null, "error": TRACEBACK, "output": what the blocks printed}``.
* ``{"command": ARGV}``: ``hybridslam ARGV`` as the console script runs it
  (:func:`hybridslam.cli.main`), in the worker's folder. Answer ``{"status": EXIT_STATUS, "stdout":
  ..., "stderr": ...}``; an exception that escapes ``main`` is exit status 1 with its traceback on
  stderr, as the console script ends.
* ``{"script": PATH, "argv": ARGV}``: ``python3 PATH ARGV`` (``runpy``, as ``__main__``) in the
  folder of ``cwd``; the same answer. The tests ask only for ``--help``.

Every answer also holds ``cpu_s``, the CPU seconds the request took in the worker; the tests' side
appends them to ``WORKDIR.docworker.cpu`` beside the worker's stderr (which example costs what).

Run as ``python3 tests/docworker.py WORKDIR [--split-cpu]``; ``--split-cpu`` gives JAX one CPU
device per core first thing, as ``hybridslam sweep`` does before its backend starts
(:func:`hybridslam.studies.strategies.split_cpu_into_cores`), so that the sweeps run here shard
their tracks as they do from the shell.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import resource
import runpy
import subprocess
import sys
import traceback
from pathlib import Path


def run_blocks(blocks: list[list]) -> tuple[dict, dict]:
    """A page's blocks (``[BLOCK_NAME, LINE, CODE]``), in order, in one fresh namespace, starting in
    float32: the namespace they leave and the answer of :func:`run_page`. In this process, whichever
    it is (the worker, or a test file's: ``tests/docblocks.py``'s :func:`run_here`)."""
    import jax

    jax.config.update("jax_enable_x64", False)  # a user's Python starts in float32: the page calls hs.setup()
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
    _close_figures()
    return namespace, {"failed": failed, "error": error, "output": output.getvalue()}


def run_page(blocks: list[list]) -> dict:
    return run_blocks(blocks)[1]


def _close_figures() -> None:
    if "matplotlib.pyplot" in sys.modules:  # one example's figures are not the next one's
        sys.modules["matplotlib.pyplot"].close("all")


def _captured(call) -> dict:
    """``call()``'s exit status (``SystemExit`` as the interpreter reads it; an escaping exception is 1,
    its traceback on stderr) and what it printed."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = call()
        except SystemExit as e:
            status = e.code
        except BaseException:  # noqa: BLE001 - the command's crash is its answer
            traceback.print_exc()
            status = 1
    if status is None:
        status = 0
    elif not isinstance(status, int):  # sys.exit("message"): printed, status 1
        print(status, file=err)
        status = 1
    _close_figures()
    return {"status": status, "stdout": out.getvalue(), "stderr": err.getvalue()}


def run_command(argv: list[str]) -> dict:
    from hybridslam.cli import main

    return _captured(lambda: main(argv))


def run_script(path: str, argv: list[str], cwd: str) -> dict:
    here, saved_argv, saved_path, saved_env = os.getcwd(), sys.argv, list(sys.path), dict(os.environ)
    os.chdir(cwd)
    sys.argv = [path, *argv]
    sys.path.insert(0, str(Path(path).resolve().parent))  # as `python3 path` puts the script's folder first
    try:
        return _captured(lambda: runpy.run_path(path, run_name="__main__"))
    finally:
        os.chdir(here)
        sys.argv, sys.path[:] = saved_argv, saved_path
        os.environ.clear()
        os.environ.update(saved_env)


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    os.chdir(sys.argv[1])
    if "--split-cpu" in sys.argv[2:]:
        from hybridslam.studies.strategies import split_cpu_into_cores

        split_cpu_into_cores()
    sys.path.insert(0, os.getcwd())  # as `python3 script.py` in the folder would
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # what is printed outside a request (by Python or by XLA) goes to stderr, not the answers
    for line in sys.stdin:
        request = json.loads(line)
        started = _cpu_seconds()
        if "page" in request:
            answer = run_page(request["blocks"])
        elif "command" in request:
            answer = run_command(request["command"])
        else:
            answer = run_script(request["script"], request["argv"], request["cwd"])
        answer["cpu_s"] = _cpu_seconds() - started
        answers.write(json.dumps(answer) + "\n")
        answers.flush()


# --------------------------------------------------------------------------- #
# The tests' side
# --------------------------------------------------------------------------- #


def environment() -> dict[str, str]:
    """This interpreter's folder first on PATH: its ``hybridslam`` entry point (a venv need not be activated)."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


class Worker:
    """One worker process in ``workdir`` (started again if a request kills it)."""

    def __init__(self, workdir: Path, *options: str):
        self.workdir, self.options, self.proc = workdir, options, None
        self.stderr = workdir.parent / f"{workdir.name}.docworker.stderr"
        self.cpu = workdir.parent / f"{workdir.name}.docworker.cpu"

    def ask(self, request: dict, what: str) -> dict | None:
        """The answer to ``request``, or ``None`` when the process ended instead (:meth:`ended`)."""
        if self.proc is None or self.proc.poll() is not None:
            env = environment()
            env["MPLBACKEND"] = "Agg"
            # A user's Python starts in float32: the pages turn float64 on themselves (hs.setup()).
            env.pop("JAX_ENABLE_X64", None)
            self.proc = subprocess.Popen([sys.executable, str(Path(__file__)), str(self.workdir), *self.options],
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                                         stderr=self.stderr.open("w"))
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline()
        if not answer:
            self.proc.wait()
            return None
        answer = json.loads(answer)
        with self.cpu.open("a", encoding="utf-8") as log:
            log.write(f"{answer['cpu_s']:8.1f}  {what}\n")
        return answer

    def ended(self) -> str:
        """What the process printed before it ended (the last 3000 characters) and its exit status."""
        assert self.proc is not None
        tail = self.stderr.read_text(encoding="utf-8", errors="replace")[-3000:]
        return f"the worker process ended: exit {self.proc.returncode}\n{tail}"

    def page(self, page: Path, root: Path, blocks: list) -> dict:
        """A page's Python blocks (``Block``s of ``tests/docblocks.py``), run as :func:`run_page` does."""
        request = [[b.name, b.line, b.code] for b in blocks]
        answer = self.ask({"page": page.name, "blocks": request}, str(page))
        if answer is None:
            return {"failed": f"{page.relative_to(root)}", "error": self.ended(), "output": ""}
        return answer

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            assert self.proc.stdin
            self.proc.stdin.close()
            self.proc.wait()


if __name__ == "__main__":
    main()
