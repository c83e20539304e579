"""Every command of the README and of the documentation pages runs, in the pages' order, as a user
types it, and the README's commands print what the README says they print; then the Python blocks
of the pages that go with the commands (``tests/docblocks.py``'s ``WITH_COMMANDS``). The other pages'
Python blocks run in ``tests/test_readme_python.py``, beside this file on CI's other worker, or in the
test file about their subject (``IN_TEST_FILES``).

The pages are those of ``tests/docblocks.py`` (the README first, then the site's navigation). Their
``bash`` commands run in one scratch folder, so each one's output is the next one's input
(``simulate`` writes the ``scenario.json`` that ``run`` reads; ``sweep`` writes the ``runs/sweep``
that ``plot`` draws); a command that two pages share runs once. The README's main job, ``hybridslam
sweep -o runs/sweep``, runs through the shell as a process of its own, from the installed entry
point: it tests the install. Every other ``hybridslam`` command runs as that entry point runs it,
:func:`hybridslam.cli.main` with the command's arguments, in one long-lived process
(``tests/docworker.py``, started as the CLI's sweep starts: one CPU device per core), so that the
interpreter's start and the imports are paid once and a program that several commands (or a page's
Python) build alike is traced and compiled once; a command with shell syntax beyond quoting (a
glob, a pipe) would run through the shell. Each page's ``python`` blocks run in order as one script
in the same folder and process, each page in a namespace of its own, starting in float32 as a
user's Python does; a failure names the page's block and line. A block after ``<!-- skip-test:
REASON -->`` is not run (``tests/test_docs_blocks.py`` reports it). Two inputs a fresh machine
lacks are supplied:

* ``MRCLAM_Dataset7``: the real dataset when ``$MRCLAM_DATASET`` names it, else the committed
  45 s excerpt of dataset 7, robot 1 (``tests/data/mrclam``). The excerpt is shorter than the
  pages' window, so on it ``--start 20 --duration 100`` becomes ``--start 0 --duration 10``: 20
  steps, a run short enough for the quick compile (``hybridslam.compilation.QUICK_RUN_STEPS``; the
  main sweep's batch compiles fully), which halves the real-data commands' time. Nothing else of
  any command line is changed.
* ``logs/``: the user's own scenario files for ``sweep --scenarios 'logs/*.json'``; here two logs
  of one robot on one map: the known-map file the MRCLAM page's ``import`` line wrote and the window
  after it, imported the same way (:data:`LATER_WINDOW`). Files of one map run as one batch, which
  is what a user's logs of one robot do.

``python3 experiments/...`` and ``python3 scripts/...`` lines (studies of minutes to hours) are
checked against the script's own ``--help`` (the script run with ``--help`` in the same process):
every option the page gives exists. The install, test and docs-build lines (``pip``, ``pytest``,
``mypy``, ``mkdocs``) are what CI itself runs.

Marked ``readme`` (minutes on 2 cores; the default study alone about 1.5 of them), so ``python3 -m
pytest -q`` skips it; ``.ci/run`` runs it in one session with the rest (``python3 -m pytest -q -m ""``),
alone it is ``python3 -m pytest -q -m readme``. A
README command without an entry in ``EXPECT`` fails here: every command of the README is checked
for what it prints.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import hybridslam as hs

from .docblocks import PAGES, README, ROOT, WITH_COMMANDS, blocks, commands, kind, python_blocks, runnable
from .docworker import Worker, environment

pytestmark = pytest.mark.readme

EXCERPT = ROOT / "tests" / "data" / "mrclam"

# Every page's commands that this test runs or checks, in order, each once; the README's alone.
COMMANDS = list(dict.fromkeys(c for p in PAGES for c in runnable(p)))
README_COMMANDS = [c for b in blocks(README) if b.lang == "bash" for c in commands(b) if kind(c) == "run"]
PYTHON_PAGES = [p for p in WITH_COMMANDS if python_blocks(p)]
# The commands that run through the shell, each a process of its own: the README's main job, which
# tests the installed entry point (every other command runs in the worker process).
SHELL = ("hybridslam sweep -o runs/sweep",)


def _scenario(path: str, **expect):
    s = hs.load_scenario(path)
    for name, value in expect.items():
        assert getattr(s, name) == value, (path, name, getattr(s, name), value)
    return s


def _result(path: str, *, smoother: str, trajectory: bool = True):
    r = hs.load_result(path)
    assert f"smoother={smoother}" in r.estimator, r.estimator
    assert r.steps and all(s.components for s in r.steps)
    assert (r.trajectory is not None) == trajectory
    return r


RUN_TABLE = [r"^\s+k\s+det\s+alive\s+entropy\s+det_cov\s+err_wmax\s+err_wavg\s+step_ms$",
             r"^compile time [\d.]+ s; \d+ steps in [\d.]+ s \([\d.]+ ms/step\)$",
             r"^translation error \(m\): online APE [\d.]+, RPE [\d.]+; smoothed APE [\d.]+, RPE [\d.]+; "
             r"last pose [\d.]+$"]


# For each README command (and some of the pages'): the lines its stdout must hold (regular
# expressions, multiline) and a check of the files it writes. Other commands of the pages must exit
# 0 without a traceback.
EXPECT: dict[str, tuple[list[str], object]] = {
    "hybridslam sweep -o runs/sweep": (
        [r"^\s*alpha\s+model\s+tracks\s+H\(w\)", r"^wrote runs/sweep/table.csv", r"^sweep finished in [\d.]+ s"],
        lambda: [Path("runs/sweep", f).stat() for f in ("table.csv", "cells.jsonl", "alpha_sweep.png")]),
    "hybridslam simulate --seed 0 --steps 10 -o scenario.json": (
        [r"^wrote scenario.json: 10 steps, 6 objects"],
        lambda: _scenario("scenario.json", num_steps=10, num_objects=6)),
    "hybridslam run scenario.json -o result.json": (
        [r"estimator=hybrid;.*smoother=full", *RUN_TABLE, r"^wrote result.json$"],
        lambda: _result("result.json", smoother="full")),
    "hybridslam run scenario.json -o ml.json --estimator ml": (
        [r"estimator=ml;.*smoother=full", *RUN_TABLE, r"^wrote ml.json$"],
        lambda: _result("ml.json", smoother="full")),
    "hybridslam plot result.json --scenario scenario.json": (
        [r"^wrote result.png$"],
        lambda: Path("result.png").stat()),
    "hybridslam import mrclam MRCLAM_Dataset7 --robot 1 --start 20 --duration 100 -o robot1.json": (
        [r"^wrote robot1.json: MRCLAM_Dataset7 robot 1, .* known map of 15 landmarks$",
         r"^motion_cov \(calibrated(, from the 5 s drift)?\): sd", r"^geometric_cov \(calibrated from the detections as written\): sd"],
        lambda: _scenario("robot1.json", num_objects=15)),
    "hybridslam import mrclam MRCLAM_Dataset7 --robot 1 --start 20 --duration 100 --unknown-map -o robot1-slam.json": (
        [r"^wrote robot1-slam.json: .* unknown map of 15 landmarks \(\d+ object slots: --object-slots\)$"],
        lambda: _scenario("robot1-slam.json", num_objects=0)),
    "hybridslam run robot1.json -o robot1-hybrid.json --capacity 16 --gate 3 --weights linearized --plot robot1-hybrid.png": (
        [r"estimator=hybrid;.*weights=linearized.*capacity=16", *RUN_TABLE, r"^wrote robot1-hybrid.json$",
         r"^wrote robot1-hybrid.png$"],
        lambda: _result("robot1-hybrid.json", smoother="full")),
    "hybridslam sweep --scenarios 'logs/*.json' --estimator max-mixture -o runs/logs": (
        [r"^sweep: 2 scenario file\(s\)", r"^wrote runs/logs/table.csv", r"^sweep finished in"],
        lambda: [Path("runs/logs", f).stat() for f in ("table.csv", "cells.jsonl", "metrics.png")]),
    "hybridslam plot runs/sweep": (
        [r"alpha_sweep.png"],
        lambda: Path("runs/sweep/alpha_sweep.png").stat()),
}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The scratch folder the README's commands run in, with ``MRCLAM_Dataset7`` in it."""
    path = tmp_path_factory.mktemp("readme")
    dataset = os.environ.get("MRCLAM_DATASET")
    (path / "MRCLAM_Dataset7").symlink_to(Path(dataset).resolve() if dataset else EXCERPT)
    return path


@pytest.fixture(scope="module")
def worker(workdir):
    """The process of every command but :data:`SHELL`'s and of :data:`PYTHON_PAGES`' blocks."""
    worker = Worker(workdir, "--split-cpu")
    yield worker
    worker.close()


def _later_window() -> list[str]:
    """The window after the pages' ``--start 20 --duration 100`` (on the excerpt: after its 10 s)."""
    return ["--start", "120", "--duration", "100"] if os.environ.get("MRCLAM_DATASET") else ["--start", "10", "--duration", "10"]


LATER_WINDOW = _later_window()


def _on_excerpt(command: str) -> str:
    """The command as it runs here: on the excerpt, a window that lies inside it."""
    if not os.environ.get("MRCLAM_DATASET"):
        command = command.replace("--start 20 --duration 100", "--start 0 --duration 10")
    return command


def _shell_line(command: str) -> str:
    """The command as the shell runs it here: the entry point of this interpreter's environment."""
    command = _on_excerpt(command)
    if shutil.which("hybridslam", path=environment()["PATH"]) is None:  # installed without scripts
        command = re.sub(r"^hybridslam ", f"{shlex.quote(sys.executable)} -m hybridslam ", command)
    return command


def _arguments(command: str) -> list[str] | None:
    """The words the shell would pass, or ``None`` when the shell would do more than split and
    unquote them (expand a glob or a variable, redirect, pipe, chain): then only the shell runs it."""
    unquoted = re.sub(r"'[^']*'|\"[^\"$`\\\\]*\"", "", command)
    if re.search(r"[*?\[\]$`~|&;<>(){}\\]", unquoted):
        return None
    return shlex.split(command)


def test_every_readme_command_has_an_expectation():
    assert "hybridslam sweep -o runs/sweep" in README_COMMANDS  # the main job
    missing = [c for c in README_COMMANDS if c not in EXPECT]
    assert not missing, f"README commands without an entry in EXPECT (add one): {missing}"
    unused = [c for c in EXPECT if c not in COMMANDS]
    assert not unused, f"EXPECT entries no page documents any more (remove them): {unused}"
    assert all(c in COMMANDS for c in SHELL), [c for c in SHELL if c not in COMMANDS]


def test_arguments_as_the_shell_splits_them():
    """The worker gets what the shell would pass; anything the shell itself expands goes to the shell."""
    assert _arguments("hybridslam sweep --scenarios 'logs/*.json' -o runs/logs") == [
        "hybridslam", "sweep", "--scenarios", "logs/*.json", "-o", "runs/logs"]
    assert _arguments('hybridslam run "my file.json" -o r.json') == ["hybridslam", "run", "my file.json", "-o", "r.json"]
    for line in ("hybridslam run logs/*.json", "hybridslam run $F", "hybridslam run a.json > out.txt",
                 "hybridslam run a.json | tee out", "hybridslam run ~/a.json", 'hybridslam run "$F"'):
        assert _arguments(line) is None, line


@pytest.mark.parametrize("command", COMMANDS)
def test_readme_command_runs(command, workdir, worker, monkeypatch):
    monkeypatch.chdir(workdir)
    if command.startswith("python3 "):
        return _check_options(command, worker)
    if "logs/" in command:
        os.makedirs("logs", exist_ok=True)
        shutil.copy("robot1.json", Path("logs") / "robot1.json")
        later = ["import", "mrclam", "MRCLAM_Dataset7", "--robot", "1", *LATER_WINDOW, "-o", "logs/robot1-later.json"]
        answer = worker.ask({"command": later}, " ".join(later))
        assert answer is not None and answer["status"] == 0, answer
    argv = _arguments(_on_excerpt(command))
    if command in SHELL or argv is None:
        proc = subprocess.run(_shell_line(command), shell=True, capture_output=True, text=True, env=environment())
        status, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    else:
        answer = worker.ask({"command": argv[1:]}, command)
        assert answer is not None, f"{command}: {worker.ended()}"
        status, stdout, stderr = answer["status"], answer["stdout"], answer["stderr"]
    assert status == 0, f"{command}\nexit {status}\n{stdout[-3000:]}\n{stderr[-3000:]}"
    assert "Traceback" not in stderr, stderr
    if command not in EXPECT:
        return
    printed, check_files = EXPECT[command]
    for pattern in printed:
        assert re.search(pattern, stdout, flags=re.M), f"{command}: no line matches {pattern!r}:\n{stdout}"
    check_files()  # type: ignore[operator]


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_python_blocks_run(page, worker):
    """A page's Python blocks, in order, as one script in the scratch folder (after the commands,
    so the files they name exist); a failure names the block and its line in the page."""
    answer = worker.page(page, ROOT, python_blocks(page))
    assert answer["failed"] is None, f"{answer['failed']} failed:\n{answer['error']}\n{answer['output'][-3000:]}"


def _check_options(command: str, worker: Worker) -> None:
    """A script line: the script exists and its ``--help`` lists every option the page gives it."""
    argv = shlex.split(command)
    script = ROOT / argv[1]
    assert script.is_file(), f"{command}: no such script {argv[1]}"
    answer = worker.ask({"script": str(script), "argv": ["--help"], "cwd": str(ROOT)}, command)
    assert answer is not None, f"{command}: {worker.ended()}"
    assert answer["status"] == 0, answer["stderr"]
    for option in (a for a in argv[2:] if a.startswith("--")):
        assert re.search(rf"(^|\s){re.escape(option)}\b", answer["stdout"]), f"{command}: {option} not in --help"
