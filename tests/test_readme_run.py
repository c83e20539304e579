"""Every code block of the README and of the documentation pages runs, in the pages' order, as a
user types it, and the README's commands print what the README says they print.

The pages are those of ``tests/docblocks.py`` (the README first, then the site's navigation). Their
``bash`` commands run as subprocesses through the shell, in one scratch folder, so each one's output
is the next one's input (``simulate`` writes the ``scenario.json`` that ``run`` reads; ``sweep``
writes the ``runs/sweep`` that ``plot`` draws); a command that two pages share runs once. Each
page's ``python`` blocks run in order as one script in the same folder, each page in a namespace of
its own, all pages in one process (``tests/docworker.py``), so that the imports and the compiles
are shared; a failure names the page's block and line. A block after ``<!-- skip-test: REASON -->``
is not run (``tests/test_docs_blocks.py`` reports it). Two inputs a
fresh machine lacks are supplied:

* ``MRCLAM_Dataset7``: the real dataset when ``$MRCLAM_DATASET`` names it, else the committed
  45 s excerpt of dataset 7, robot 1 (``tests/data/mrclam``). The excerpt is shorter than the
  pages' window, so on it ``--start 20 --duration 100`` becomes ``--start 0 --duration 40``;
  nothing else of any command line is changed.
* ``logs/``: the user's own scenario files for ``sweep --scenarios 'logs/*.json'``; here the two
  files the MRCLAM page's ``import`` lines wrote.

``python3 experiments/...`` and ``python3 scripts/...`` lines (studies of minutes to hours) are
checked against the script's own ``--help``: every option the page gives exists. The install,
test and docs-build lines (``pip``, ``pytest``, ``mypy``, ``mkdocs``) are what CI itself runs.

Marked ``readme`` (minutes on 2 cores; the default study alone about 1.5 of them), so ``python3 -m
pytest -q`` skips it; ``.ci/run`` runs it in one session with the rest (``python3 -m pytest -q -m ""``),
alone it is ``python3 -m pytest -q -m readme``. A
README command without an entry in ``EXPECT`` fails here: every command of the README is checked
for what it prints.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import hybridslam as hs

from .docblocks import PAGES, README, ROOT, blocks, commands, kind

pytestmark = pytest.mark.readme

EXCERPT = ROOT / "tests" / "data" / "mrclam"

# Every page's commands that this test runs or checks, in order, each once; the README's alone.
COMMANDS = list(dict.fromkeys(c for p in PAGES for b in blocks(p) if b.lang == "bash" and b.skip is None
                              for c in commands(b) if kind(c) in ("run", "script")))
README_COMMANDS = [c for b in blocks(README) if b.lang == "bash" for c in commands(b) if kind(c) == "run"]
PYTHON_PAGES = [p for p in PAGES if any(b.lang == "python" and b.skip is None for b in blocks(p))]



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
    "hybridslam run scenario.json -o ml.json --estimator ml --smoother filter": (
        [r"estimator=ml;.*smoother=filter", *RUN_TABLE[:2], r"^wrote ml.json$"],
        lambda: _result("ml.json", smoother="filter", trajectory=False)),
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


def _shell_line(command: str) -> str:
    """The command as the shell runs it here: on the excerpt, a window that lies inside it."""
    if not os.environ.get("MRCLAM_DATASET"):
        command = command.replace("--start 20 --duration 100", "--start 0 --duration 40")
    if shutil.which("hybridslam", path=_environment()["PATH"]) is None:  # installed without scripts
        command = re.sub(r"^hybridslam ", f"{shlex.quote(sys.executable)} -m hybridslam ", command)
    return command


def _environment() -> dict[str, str]:
    """This interpreter's folder first on PATH: its ``hybridslam`` entry point (a venv need not be activated)."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def test_every_readme_command_has_an_expectation():
    assert "hybridslam sweep -o runs/sweep" in README_COMMANDS  # the main job
    missing = [c for c in README_COMMANDS if c not in EXPECT]
    assert not missing, f"README commands without an entry in EXPECT (add one): {missing}"
    unused = [c for c in EXPECT if c not in COMMANDS]
    assert not unused, f"EXPECT entries no page documents any more (remove them): {unused}"


@pytest.mark.parametrize("command", COMMANDS)
def test_readme_command_runs(command, workdir, monkeypatch):
    monkeypatch.chdir(workdir)
    if command.startswith("python3 "):
        return _check_options(command)
    if "logs/" in command:
        os.makedirs("logs", exist_ok=True)
        for name in ("robot1.json", "robot1-slam.json"):
            shutil.copy(name, Path("logs") / name)
    proc = subprocess.run(_shell_line(command), shell=True, capture_output=True, text=True, env=_environment())
    assert proc.returncode == 0, f"{command}\nexit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert "Traceback" not in proc.stderr, proc.stderr
    if command not in EXPECT:
        return
    printed, check_files = EXPECT[command]
    for pattern in printed:
        assert re.search(pattern, proc.stdout, flags=re.M), f"{command}: no line matches {pattern!r}:\n{proc.stdout}"
    check_files()  # type: ignore[operator]


class _Worker:
    """One ``tests/docworker.py`` process for every page's Python blocks (imports and compiles shared);
    started again if a page kills it."""

    def __init__(self, workdir: Path):
        self.workdir, self.proc = workdir, None
        self.stderr = workdir.parent / "docworker.stderr"

    def run(self, page: Path) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            env = _environment()
            env["MPLBACKEND"] = "Agg"
            # A user's Python starts in float32: the pages turn float64 on themselves (hs.setup()).
            env.pop("JAX_ENABLE_X64", None)
            self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "docworker.py"), str(self.workdir)],
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                                         stderr=self.stderr.open("w"))
        request = [[b.name, b.line, b.code] for b in blocks(page) if b.lang == "python" and b.skip is None]
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(json.dumps({"page": page.name, "blocks": request}) + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline()
        if not answer:
            self.proc.wait()
            tail = self.stderr.read_text(encoding="utf-8", errors="replace")[-3000:]
            return {"failed": f"{page.relative_to(ROOT)} (the process ended: exit {self.proc.returncode})",
                    "error": tail, "output": ""}
        return json.loads(answer)

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            assert self.proc.stdin
            self.proc.stdin.close()
            self.proc.wait()


@pytest.fixture(scope="module")
def python_worker(workdir):
    worker = _Worker(workdir)
    yield worker
    worker.close()


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_python_blocks_run(page, python_worker):
    """A page's Python blocks, in order, as one script in the scratch folder (after the commands,
    so the files they name exist); a failure names the block and its line in the page."""
    answer = python_worker.run(page)
    assert answer["failed"] is None, f"{answer['failed']} failed:\n{answer['error']}\n{answer['output'][-3000:]}"


def _check_options(command: str) -> None:
    """A script line: the script exists and its ``--help`` lists every option the README gives it."""
    argv = shlex.split(command)
    script = ROOT / argv[1]
    assert script.is_file(), f"{command}: no such script {argv[1]}"
    proc = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    for option in (a for a in argv[2:] if a.startswith("--")):
        assert re.search(rf"(^|\s){re.escape(option)}\b", proc.stdout), f"{command}: {option} not in --help"

