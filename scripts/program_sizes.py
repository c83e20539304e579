"""Size of every estimator's compiled step program: jaxpr equations and the CPU seconds to build it.

For each estimator (and the main option variants) the 5-step :func:`hybridslam.driver.scan` on
``hybridslam.simulate(0, steps=5)`` is traced (``jax.jit(f).trace``), lowered to StableHLO and
compiled by XLA; the script prints the number of jaxpr equations (nested jaxprs included: the scan
body, ``cond`` branches, ``while`` loops, ``custom_jvp`` / ``custom_vjp`` calls, pjit) and the CPU
seconds (``time.process_time``, all threads of the process) of each of the three stages. The
equation count is exact and repeatable; the seconds depend on the machine and its load, so compare
two versions in alternating runs on the same machine. Asserts nothing.

    python scripts/program_sizes.py                      # every variant
    python scripts/program_sizes.py --only ml hybrid     # variants whose label starts so
    python scripts/program_sizes.py --no-compile         # equations, trace and lowering only

The persistent compilation cache is not used (each compile is cold).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Iterator

os.environ.setdefault("HYBRIDSLAM_NO_CACHE", "1")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

import hybridslam as hs  # noqa: E402
from hybridslam.driver import inputs_from_scenario, scan  # noqa: E402

hs.setup()

# (label, estimator name, options): the defaults and the options that change the program most.
VARIANTS: tuple[tuple[str, str, dict], ...] = (
    ("hybrid", "hybrid", {}),
    ("hybrid weights=linearized", "hybrid", {"weights": "linearized"}),
    ("hybrid weights=sampled", "hybrid", {"weights": "sampled"}),
    ("hybrid smoother=filter", "hybrid", {"smoother": "filter"}),
    ("ml", "ml", {}),
    ("ml smoother=filter", "ml", {"smoother": "filter"}),
    ("gpda", "gpda", {}),
    ("max-mixture", "max-mixture", {}),
    ("multimodal", "multimodal", {}),
    ("multimodal smoother=filter", "multimodal", {"smoother": "filter"}),
)


def _sub_jaxprs(value) -> Iterator[jax.extend.core.Jaxpr]:
    if isinstance(value, jax.extend.core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jax.extend.core.Jaxpr):
        yield value
    elif isinstance(value, tuple | list):
        for v in value:
            yield from _sub_jaxprs(v)


def count_equations(jaxpr: jax.extend.core.Jaxpr) -> int:
    """Equations of ``jaxpr`` and of every jaxpr nested in its equations' parameters."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for param in eqn.params.values():
            for sub in _sub_jaxprs(param):
                total += count_equations(sub)
    return total


def measure(name: str, options: dict, steps: int, compile_: bool) -> tuple[int, float, float, float]:
    """``(equations, trace s, lower s, compile s)`` of the ``steps``-step scan of one estimator."""
    scenario = hs.simulate(0, steps=steps)
    est = hs.make_estimator(name, **options)
    state = est.init(scenario)
    slots = jax.eval_shape(est.view, state).history.shape[-1]
    inputs = jax.tree.map(np.asarray, inputs_from_scenario(scenario, slots))
    key = jax.random.PRNGKey(0)
    dynamic, static = eqx.partition((est, state), eqx.is_array)

    def program(dynamic, inputs, key):
        est, state = eqx.combine(dynamic, static)
        return scan(est, state, inputs, key)

    t0 = time.process_time()
    traced = jax.jit(program).trace(dynamic, inputs, key)
    t1 = time.process_time()
    lowered = traced.lower()
    t2 = time.process_time()
    if compile_:
        lowered.compile()
    t3 = time.process_time()
    return count_equations(traced.jaxpr.jaxpr), t1 - t0, t2 - t1, t3 - t2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="+", default=None, help="labels to measure (prefixes)")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--no-compile", action="store_true", help="skip the XLA compile")
    args = parser.parse_args()
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, {args.steps}-step scan of hs.simulate(0)")
    print(f"{'variant':<28} {'equations':>9} {'trace s':>8} {'lower s':>8} {'compile s':>9} {'total s':>8}")
    for label, name, options in VARIANTS:
        if args.only and not any(label.startswith(p) for p in args.only):
            continue
        eqns, tr, lo, co = measure(name, options, args.steps, not args.no_compile)
        comp = f"{co:>9.2f}" if not args.no_compile else f"{'-':>9}"
        print(f"{label:<28} {eqns:>9} {tr:>8.2f} {lo:>8.2f} {comp} {tr + lo + co:>8.2f}", flush=True)
        jax.clear_caches()


if __name__ == "__main__":
    main()
