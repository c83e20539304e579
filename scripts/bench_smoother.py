"""The smoother's linear solve and one Levenberg-Marquardt solve, per elimination order and problem size.

For each size (poses P, objects N; the hallway is P = 61, N = 70, an MRCLAM window P = 201, N = 15,
the paper setup P = 11, N = 6) a random range-bearing graph with 4 detections per pose is
linearized once; the script prints the median time of ``solve_normal`` for each elimination order
(``poses-first``: block-tridiagonal scan then a Schur complement onto the objects, the default;
``objects-first``; ``dense``: the reference) and of a whole ``solve`` (10 iterations at most) from a
perturbed start. The graph's prior couples no two objects, so ``objects-first`` is timed twice:
with the object part ``C`` inverted densely (``dense C``) and block by block (``blocks``, what
``FactorGraph.independent_objects`` selects and every run's smoother uses); the LM solve and the
Laplace marginal (``marginal``, of the middle pose) use the blocks. Asserts nothing; run it on an
idle machine.

    python scripts/bench_smoother.py [--sizes 11x6,61x70,201x15] [--repeats 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import hybridslam
from hybridslam.inference import smoother as sm

hybridslam.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

DETECTIONS_PER_POSE = 4


def graph(p: int, n: int, seed: int = 0) -> tuple[sm.FactorGraph, jax.Array, jax.Array]:
    """A random graph: a circle of poses among ``n`` objects, each pose seeing 4 random objects."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2.0 * np.pi, p)
    poses = np.stack([10 * np.cos(angle), 10 * np.sin(angle), angle + np.pi / 2], axis=1)
    objects = np.concatenate([rng.uniform(-12, 12, (n, 2)), np.zeros((n, 1))], axis=1)
    f = p * DETECTIONS_PER_POSE
    pose_of = np.repeat(np.arange(p), DETECTIONS_PER_POSE)
    obj_of = rng.integers(0, n, f)
    d = objects[obj_of, :2] - poses[pose_of, :2]
    z = np.stack([np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0]) - poses[pose_of, 2]], axis=1)
    z += rng.normal(0, [0.05, 0.01], z.shape)
    odo = np.stack([np.asarray(hybridslam.models.se2.between(jnp.asarray(poses[i]), jnp.asarray(poses[i + 1])))
                    for i in range(p - 1)])
    prior_info = np.eye(3 + 3 * n) * 100.0
    g = sm.FactorGraph(
        prior_mean=jnp.asarray(np.concatenate([poses[0], objects.reshape(-1)])),
        prior_sqrt_info=jnp.asarray(np.sqrt(prior_info) * 0.1),
        odometry=jnp.asarray(odo), odometry_active=jnp.ones(p - 1, bool),
        motion_sqrt_info=jnp.asarray(np.diag([10.0, 10.0, 30.0])),
        meas_pose=jnp.asarray(pose_of), meas_objects=jnp.asarray(obj_of[:, None]),
        meas_log_weight=jnp.zeros((f, 1)), meas_null_log_weight=jnp.full(f, -jnp.inf),
        meas_data=jnp.asarray(z), pose_active=jnp.ones(p, bool), object_active=jnp.ones(n, bool),
        residual_fn=sm.RangeBearingResidual(jnp.asarray(np.diag([20.0, 100.0]))),
    )
    start = poses + rng.normal(0, [0.2, 0.2, 0.02], poses.shape)
    return g, jnp.asarray(start), jnp.asarray(objects)


def median_ms(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="11x6,61x70,201x15")
    parser.add_argument("--repeats", type=int, default=20)
    a = parser.parse_args()
    print(f"{'P':>5} {'N':>4} {'poses-first':>12} {'obj-first dense C':>18} {'obj-first blocks':>17} {'dense':>8} "
          f"{'marginal':>9} {'solve (LM)':>11} {'iters':>6}  ms")
    for size in a.sizes.split(","):
        p, n = (int(v) for v in size.split("x"))
        g, poses, objects = graph(p, n)
        blocks = dataclasses.replace(g, independent_objects=True)
        lin = jax.jit(sm.linearize)(g, poses, objects)
        lin_blocks = jax.jit(sm.linearize)(blocks, poses, objects)
        normal = lambda m: jax.jit(lambda lin: sm.solve_normal(lin, m))  # noqa: E731
        row = [median_ms(normal("poses-first"), lin, repeats=a.repeats),
               median_ms(normal("objects-first"), lin, repeats=a.repeats),
               median_ms(normal("objects-first"), lin_blocks, repeats=a.repeats),
               median_ms(normal("dense"), lin, repeats=a.repeats)]
        solve = jax.jit(lambda g, x, o: sm.solve(g, x, o, max_steps=10))
        sol = solve(blocks, poses, objects)
        marg = median_ms(jax.jit(lambda s: sm.marginal(s, p // 2)), sol, repeats=a.repeats)
        lm = median_ms(solve, blocks, poses, objects, repeats=max(3, a.repeats // 4))
        print(f"{p:>5} {n:>4} {row[0]:>12.2f} {row[1]:>18.2f} {row[2]:>17.2f} {row[3]:>8.2f} {marg:>9.2f} {lm:>11.1f} "
              f"{int(sol.steps):>6}", flush=True)

if __name__ == "__main__":
    main()
