"""Regenerate the golden result files of ``tests/data/golden`` (``tests/test_golden.py``).

Each case of ``tests/data/golden/cases.json`` names a scenario file of that folder (without
``.json``), an estimator and the options of :func:`hybridslam.run_estimator`; the case ``NAME`` is
run with seed 0 exactly as ``tests/test_golden.py`` runs it, and its result file (``timing``
removed) is written to ``NAME.result.json`` as ``indent=1`` JSON. XLA runs with the test suite's
settings (``jax_disable_most_optimizations`` and XLA's elemental emitters, ``tests/conftest.py``):
optimizations and code generators change the last bits of the numbers.

Run it only for a change that is *meant* to change numbers, and say why in the commit message
(``tests/data/golden/README.md``). ``--check`` writes nothing: it compares every case with its
file the way the test does (the ``steps``) and also says whether the rest of the file (the
``estimator`` text, ...) would change.

    python3 scripts/make_golden.py [CASE ...] [--check] [-o FOLDER]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax

import hybridslam as hs
from hybridslam.driver import use_elemental_emitters_everywhere
from hybridslam.io.result import result_to_json

hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

jax.config.update("jax_disable_most_optimizations", True)  # the test suite's setting, before anything compiles
use_elemental_emitters_everywhere()  # the test suite's XLA_FLAGS too (tests/conftest.py)

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
GOLDEN = os.path.join(ROOT, "tests", "data", "golden")
sys.path.insert(0, ROOT)
from tests.golden import differences  # noqa: E402  (the comparison tests/test_golden.py makes)


def golden_json(folder: str, case: dict) -> dict:
    """The result file's JSON object of one case, ``timing`` removed (as ``tests/test_golden.py`` has it)."""
    scenario = hs.load_scenario(os.path.join(folder, case["scenario"] + ".json"))
    run = hs.run_estimator(scenario, case["estimator"], seed=0, **case["settings"])
    got = json.loads(json.dumps(result_to_json(run.result, version=1)))  # the files are format 1
    got.pop("timing", None)
    return got


def text(obj) -> str:
    """The file's bytes: ``indent=1`` JSON, no trailing newline (as the committed files are)."""
    return json.dumps(obj, indent=1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cases", nargs="*", help="case names of cases.json (default: every case)")
    p.add_argument("--golden", default=GOLDEN, help="the folder of cases.json and the scenario files")
    p.add_argument("-o", "--output", default=None, help="write the result files here (default: --golden)")
    p.add_argument("--check", action="store_true", help="write nothing; compare with the files in --golden")
    args = p.parse_args(argv)
    with open(os.path.join(args.golden, "cases.json"), encoding="utf-8") as f:
        cases = json.load(f)
    unknown = [name for name in args.cases if name not in cases]
    if unknown:
        p.error(f"unknown case(s) {', '.join(unknown)} (cases.json has: {', '.join(sorted(cases))})")
    output = args.golden if args.output is None else args.output
    if not args.check:
        os.makedirs(output, exist_ok=True)
    failed = 0
    for name in args.cases or sorted(cases):
        got = golden_json(args.golden, cases[name])
        path = os.path.join(args.golden if args.check else output, name + ".result.json")
        if not args.check:
            with open(path, "w", encoding="utf-8") as f:
                f.write(text(got))
            print(f"wrote {path}", flush=True)
            continue
        try:
            with open(path, encoding="utf-8") as f:
                old = f.read()
        except FileNotFoundError:
            print(f"{name}: MISSING {path}", flush=True)
            failed += 1
            continue
        want = json.loads(old)
        if diff := differences(got["steps"], want["steps"]):
            failed += 1
            verdict = f"DIFFERENT steps (tests/test_golden.py fails): {len(diff)} difference(s), first {diff[0]}"
        elif text(got) != old:
            differ = [k for k in dict.fromkeys([*want, *got]) if text(got.get(k)) != text(want.get(k))]
            notes = [f"{k} (the test passes: equal to its tolerance, tests/golden.py, but not bit for bit)"
                     if k == "steps" else k for k in differ]
            verdict = f"same steps as the test compares them; the file's bytes would change in {', '.join(notes)}"
        else:
            verdict = "identical, byte for byte"
        print(f"{name}: {verdict}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
