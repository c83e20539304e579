"""An independent, plain-numpy implementation of the paper's hybrid belief: the reference that
``hybridslam sweep`` is measured against (issue 48).

Tchuiev, Feldman & Indelman (IROS 2019), Algorithm 1, written from the paper alone (it imports
nothing from hybridslam and reads the scenario files as JSON, docs/file_format.md):

* the belief is a set of weighted Gaussian components, one per (class realization ``C``,
  association history ``β_1:k``) (Eq. 5); each component is one EKF over ``[x_k, x^o_1..N]``;
* propagate every component with the motion model ``x_k = x_{k-1} ∘ u_k ∘ Exp(w)`` (Eq. 11,
  Algorithm 1 line 3);
* split every component over every injective assignment ``β_k`` of the step's detections to
  objects, and over the classes of the objects a child associates for the first time (lazy class
  realizations, Sec. IV-D; prior ``class_prior``, Eq. 3);
* weigh each child by Eq. 16: the parent's weight times the mean, over ``n_s`` draws of
  ``[x_k, X^o]`` from the propagated component (Eq. 17), of the measurement likelihood (Eq. 10:
  range-bearing and the viewpoint-dependent classifier of Eq. 18) times the 0/1 object
  observation model (every associated object in the field of view);
* prune children below ``w_max / 150`` (Sec. V) and keep the ``capacity`` heaviest;
* update each kept child with its detections (Eq. 9-10) by an iterated EKF (Gauss-Newton in
  Kalman form on the same factors).

Known maps only (no ``discovery``; ``sensor.clutter_log_density`` is refused), classifier models
``mirror`` and ``none``. The generator (``generate``) is independent of ``hybridslam.simulate``:
the paper's six-object layout with a tight robot prior drawn around the true start, the
``mirror`` classifier, and a detector that reports each object in view with probability 0.9, at
most three per step, in random order.

    python scripts/numpy_reference.py generate DIR [--count 64] [--steps 10] [--seed 0]
    python scripts/numpy_reference.py run DIR_OR_FILES... [--samples 1000] [--capacity 16] [-o summary.json]

``run`` prints, per file, the final best hypothesis and each object's class posterior, and the
wall time; ``-o`` writes them as JSON (``{"files": {path: {...}}, "seconds": s}``).
"""

from __future__ import annotations

import argparse
import functools
import glob
import itertools
import json
import math
import os
import sys
import time

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
PRUNE_RATIO = 150.0  # Sec. V: prune below w_max / 150
IEKF_ITERATIONS = 20
IEKF_TOLERANCE = 1e-6


# ----------------------------------------------------------------------------- SE(2) and models


def wrap(a):
    """Angles to [-π, π)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a, b):
    """``a ∘ b`` of poses ``[x, y, θ]``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], float(wrap(a[2] + b[2]))])


def se2_exp(xi):
    """The SE(2) exponential of a tangent vector ``[v_x, v_y, ω]``."""
    t = xi[2]
    a, b = (1.0, 0.0) if abs(t) < 1e-9 else (math.sin(t) / t, (1.0 - math.cos(t)) / t)
    return np.array([a * xi[0] - b * xi[1], b * xi[0] + a * xi[1], t])


def mirror_means(theta, alpha):
    """Eq. 18: ``h_0(θ)`` and its mirror ``h_1(θ)``, shape ``(..., 2 classes, 2 scores)``."""
    s = np.sin(theta / 2.0) ** 2
    h0 = np.stack([alpha * s + 1.0 - alpha, alpha - alpha * s], axis=-1)
    return np.stack([h0, h0[..., ::-1]], axis=-2)


def mirror_cov(k):
    """``Σ_c = (RᵀR)⁻¹`` with ``R = K [[1, -0.5], [0, 1]]`` (Sec. V)."""
    r = k * np.array([[1.0, -0.5], [0.0, 1.0]])
    return np.linalg.inv(r.T @ r)


class Scenario:
    """What the filter needs of a scenario file (docs/file_format.md), read with ``json``."""

    def __init__(self, path: str):
        with open(path) as f:
            d = json.load(f)
        if d.get("format") != "hybridslam-scenario/1":
            raise ValueError(f"{path}: format: expected 'hybridslam-scenario/1', got {d.get('format')!r}")
        if d.get("discovery") is not None:
            raise ValueError(f"{path}: discovery: unknown maps are not part of the paper's model")
        if d["sensor"].get("clutter_log_density") is not None:
            raise ValueError(f"{path}: sensor.clutter_log_density: clutter is not part of the paper's model")
        self.path = path
        self.num_classes = int(d["num_classes"])
        self.obj_mean = np.array([o["prior_mean"] for o in d["objects"]], float).reshape(-1, 3)
        self.obj_cov = np.array([o["prior_cov"] for o in d["objects"]], float).reshape(-1, 3, 3)
        n = self.obj_mean.shape[0]
        prior = d.get("class_prior")
        self.class_prior = np.full((n, self.num_classes), 1.0 / self.num_classes) if prior is None else np.array(prior)
        self.robot_mean = np.array(d["robot"]["prior_mean"], float)
        self.robot_cov = np.array(d["robot"]["prior_cov"], float)
        self.motion_cov = np.array(d["motion_cov"], float)
        self.geo_cov = np.array(d["geometric_cov"], float)
        c = d["classifier"]
        self.model = c["model"]
        if self.model == "mirror":
            if self.num_classes != 2:
                raise ValueError(f"{path}: classifier.model: mirror needs num_classes 2")
            self.alpha, self.sem_cov = float(c["alpha"]), mirror_cov(float(c["K"]))
        elif self.model != "none":
            raise ValueError(f"{path}: classifier.model: {self.model!r} is not implemented here (mirror, none)")
        self.max_range, self.fov = float(d["sensor"]["max_range"]), float(d["sensor"]["fov"])
        self.odometry = [np.array(s["odometry"], float) for s in d["steps"]]
        self.detections = [(np.array([[z["range"], z["bearing"]] for z in s["detections"]], float).reshape(-1, 2),
                            np.array([z["scores"] for z in s["detections"]], float).reshape(-1, self.num_classes))
                           for s in d["steps"]]
        self.true_classes = [o.get("true_class") for o in d["objects"]]

    @property
    def num_objects(self) -> int:
        return self.obj_mean.shape[0]


def predict(x, o):
    """Range, bearing and viewpoint (Eq. 10, docs/file_format.md) of objects ``o`` (..., 3) from
    robot poses ``x`` (..., 3), and the robot-to-object offset."""
    d = o[..., :2] - x[..., :2]
    rng = np.hypot(d[..., 0], d[..., 1])
    bearing = wrap(np.arctan2(d[..., 1], d[..., 0]) - x[..., 2])
    view = wrap(np.arctan2(-d[..., 1], -d[..., 0]) - o[..., 2])
    return rng, bearing, view, d


def gauss_logpdf(r, cov):
    """``log N(r; 0, cov)`` over the last axis of ``r``."""
    inv = np.linalg.inv(cov)
    return -0.5 * np.einsum("...i,ij,...j->...", r, inv, r) - 0.5 * (np.linalg.slogdet(cov)[1] + cov.shape[0] * LOG_2PI)


# ----------------------------------------------------------------------------- one component


class Component:
    """One hypothesis: weight, class realization (``-1`` open), association history, EKF."""

    __slots__ = ("classes", "cov", "history", "log_w", "mean")

    def __init__(self, log_w, classes, history, mean, cov):
        self.log_w, self.classes, self.history, self.mean, self.cov = log_w, classes, history, mean, cov


def propagate(mean, cov, u, motion_cov):
    """EKF prediction through ``x_k = x_{k-1} ∘ u ∘ Exp(w)`` (Eq. 11); objects are static."""
    x = mean[:3]
    c, s = math.cos(x[2]), math.sin(x[2])
    f_x = np.array([[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]])
    th = x[2] + u[2]  # ∂(x ∘ u ∘ Exp(w))/∂w at w = 0 is the rotation of x ∘ u
    f_w = np.array([[math.cos(th), -math.sin(th), 0.0], [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
    new = cov.copy()
    new[:3, :] = f_x @ cov[:3, :]
    new[:, :3] = new[:, :3] @ f_x.T
    new[:3, :3] += f_w @ motion_cov @ f_w.T
    m = mean.copy()
    m[:3] = compose(x, u)
    return m, 0.5 * (new + new.T)


def log_likelihood_table(sc: Scenario, samples, geo, scores):
    """``log P(z_j | x, x^o_n, c)`` (Eq. 10) for every sample, detection, object and class,
    ``(S, J, N, M)``, and whether object ``n`` is in view in each sample, ``(S, N)``."""
    n = sc.num_objects
    x = samples[:, None, :3]
    o = samples[:, 3:].reshape(-1, n, 3)
    rng, bearing, view, _ = predict(x, o)  # (S, N)
    r = np.stack([geo[None, :, None, 0] - rng[:, None, :], wrap(geo[None, :, None, 1] - bearing[:, None, :])], -1)
    table = gauss_logpdf(r, sc.geo_cov)[..., None]  # (S, J, N, 1)
    if sc.model == "mirror":
        h = mirror_means(view, sc.alpha)  # (S, N, M, 2)
        table = table + gauss_logpdf(scores[None, :, None, None, :] - h[:, None], sc.sem_cov)  # (S, J, N, M)
    else:
        table = np.broadcast_to(table, table.shape[:3] + (sc.num_classes,))
    visible = (rng <= sc.max_range) & ((sc.fov >= 2 * np.pi) | (np.abs(bearing) <= sc.fov / 2))
    return table, visible


@functools.cache
def _grid(n: int, j_count: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Every injective assignment of ``j_count`` detections to ``n`` objects, ``(P, J)``, and every
    class per slot, ``(M^J, J)``."""
    perms = np.array(list(itertools.permutations(range(n), j_count)), dtype=int).reshape(-1, j_count)
    combos = np.array(list(itertools.product(range(m), repeat=j_count)), dtype=int).reshape(-1, j_count)
    return perms, combos


def children(sc: Scenario, comp: Component, mean, cov, geo, scores, samples_eps):
    """Every child of one propagated component with its ``log w`` (Eq. 16): ``(log_w (C,), assign
    (C, J), classes (C, N))``; ``assign[c, j]`` is detection ``j``'s object in child ``c``."""
    j_count, n, m = geo.shape[0], sc.num_objects, sc.num_classes
    if j_count == 0:
        return np.array([comp.log_w]), np.zeros((1, 0), int), comp.classes[None, :]
    chol = np.linalg.cholesky(cov)
    samples = mean[None, :] + samples_eps @ chol.T  # draws from b⁻ (Eq. 17, Alg. 1 PropWeights line 4)
    table, visible = log_likelihood_table(sc, samples, geo, scores)
    perms, combos = _grid(n, j_count, m)
    known = comp.classes[perms]  # (P, J): the component's class of each associated object, -1 open
    # A slot realizes its object's class when the object is open (lazy realizations, Sec. IV-D);
    # without a classifier every realization weighs the same, so objects stay open.
    opened = (known < 0) & (sc.model != "none")
    # Unused combo entries must be 0, so that no child is counted twice.
    valid = np.all(opened[:, None, :] | (combos[None, :, :] == 0), axis=-1)  # (P, Mc)
    p_idx, c_idx = np.nonzero(valid)
    assign = perms[p_idx]  # (C, J)
    slot_cls = np.where(opened[p_idx], combos[c_idx], np.maximum(known[p_idx], 0))
    classes = np.repeat(comp.classes[None, :], len(p_idx), axis=0)
    rows = np.arange(len(p_idx))[:, None]
    classes[rows, assign] = np.where(opened[p_idx], slot_cls, classes[rows, assign])
    log_prior = np.sum(np.where(opened[p_idx], np.log(sc.class_prior[assign, slot_cls]), 0.0), axis=-1)
    # Per draw: the product of the slots' likelihoods times the 0/1 object observation model.
    terms = np.sum(table[:, np.arange(j_count)[None, :], assign, slot_cls], axis=-1)  # (S, C)
    terms = np.where(np.all(visible[:, assign], axis=-1), terms, -np.inf)
    top = np.max(terms, axis=0)
    safe = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        psi = safe + np.log(np.mean(np.exp(terms - safe[None, :]), axis=0))  # log of Alg. 1's ψ
    keep = np.isfinite(psi)
    return (comp.log_w + log_prior + psi)[keep], assign[keep], classes[keep]


def update(sc: Scenario, mean, cov, assign, classes, geo, scores):
    """The posterior of one child (Eq. 9-10): iterated EKF on its detections' range, bearing and
    (``mirror``) scores; covariance ``(I - K H) P`` at the last iterate."""
    if not assign:
        return mean, cov
    n_state = mean.shape[0]
    sem = sc.model == "mirror"
    rows = 4 if sem else 2
    noise = np.zeros((rows * len(assign),) * 2)
    block = sc.geo_cov if not sem else np.block([[sc.geo_cov, np.zeros((2, 2))], [np.zeros((2, 2)), sc.sem_cov]])
    for j in range(len(assign)):
        noise[rows * j:rows * (j + 1), rows * j:rows * (j + 1)] = block
    y = mean.copy()
    for _ in range(IEKF_ITERATIONS):
        resid = np.zeros(rows * len(assign))
        h = np.zeros((rows * len(assign), n_state))
        for j, obj in enumerate(assign):
            x, o = y[:3], y[3 + 3 * obj:6 + 3 * obj]
            rng, bearing, view, d = predict(x, o)
            r2 = rng * rng
            oi = 3 + 3 * obj
            k = rows * j
            resid[k:k + 2] = [geo[j, 0] - rng, wrap(geo[j, 1] - bearing)]
            h[k, 0:2], h[k, oi:oi + 2] = -d / rng, d / rng
            h[k + 1, 0:2], h[k + 1, 2], h[k + 1, oi:oi + 2] = [d[1] / r2, -d[0] / r2], -1.0, [-d[1] / r2, d[0] / r2]
            if sem:
                c = classes[obj]
                resid[k + 2:k + 4] = scores[j] - mirror_means(np.asarray(view), sc.alpha)[c]
                ds = sc.alpha * math.sin(view) / 2.0 * (np.array([1.0, -1.0]) if c == 0 else np.array([-1.0, 1.0]))
                dview_dx = np.array([d[1] / r2, -d[0] / r2])  # ∂viewpoint/∂robot position
                h[k + 2:k + 4, 0:2] = np.outer(ds, dview_dx)
                h[k + 2:k + 4, oi:oi + 2] = np.outer(ds, -dview_dx)
                h[k + 2:k + 4, oi + 2] = -ds
        delta = mean - y
        delta[2::3] = wrap(delta[2::3])
        s = h @ cov @ h.T + noise
        gain = np.linalg.solve(s, h @ cov).T
        new = mean + gain @ (resid - h @ delta)
        new[2::3] = wrap(new[2::3])
        step = new - y
        step[2::3] = wrap(step[2::3])
        y = new
        if np.max(np.abs(step)) < IEKF_TOLERANCE:
            break
    post = (np.eye(n_state) - gain @ h) @ cov
    return y, 0.5 * (post + post.T)


def run(sc: Scenario, samples: int = 1000, capacity: int = 16, seed: int = 0) -> list[Component]:
    """Algorithm 1 over every step of ``sc``; the final components, heaviest first."""
    n = sc.num_objects
    rng = np.random.default_rng(seed)
    mean = np.concatenate([sc.robot_mean, sc.obj_mean.reshape(-1)])
    cov = np.zeros((3 + 3 * n,) * 2)
    cov[:3, :3] = sc.robot_cov
    for i in range(n):
        cov[3 + 3 * i:6 + 3 * i, 3 + 3 * i:6 + 3 * i] = sc.obj_cov[i]
    belief = [Component(0.0, np.full(n, -1), [], mean, cov)]
    for u, (geo, scores) in zip(sc.odometry, sc.detections):
        eps = rng.standard_normal((samples, 3 + 3 * n))
        log_w, kids = [], []
        for comp in belief:
            m, p = propagate(comp.mean, comp.cov, u, sc.motion_cov)
            lw, assign, classes = children(sc, comp, m, p, geo, scores, eps)
            log_w.append(lw)
            kids += [(a, c, comp, m, p) for a, c in zip(assign, classes)]
        w = np.concatenate(log_w)
        if not kids:
            raise ValueError(f"{sc.path}: no hypothesis explains a step's detections")
        top = np.max(w)
        order = np.argsort(-w, kind="stable")  # Alg. 1 PruneAndNormalize: below w_max / 150, then capacity
        keep = order[w[order] >= top - math.log(PRUNE_RATIO)][:capacity]
        total = top + math.log(np.sum(np.exp(w[keep] - top)))
        belief = []
        for i in keep:
            a, c, parent, m, p = kids[i]
            m2, p2 = update(sc, m, p, [int(o) for o in a], c, geo, scores)
            belief.append(Component(w[i] - total, c, parent.history + [[int(o) for o in a]], m2, p2))
    return belief


def class_posterior(sc: Scenario, belief: list[Component]) -> np.ndarray:
    """``P(c_n = c | H_k)`` (Eq. 7): an open object keeps its prior in its component."""
    post = np.zeros((sc.num_objects, sc.num_classes))
    for comp in belief:
        w = math.exp(comp.log_w)
        for i, c in enumerate(comp.classes):
            post[i] += w * (sc.class_prior[i] if c < 0 else np.eye(sc.num_classes)[c])
    return post


def summarize(sc: Scenario, belief: list[Component]) -> dict:
    best = belief[0]
    return {"weights": [math.exp(c.log_w) for c in belief], "best_associations": best.history,
            "best_classes": best.classes.tolist(), "best_pose": best.mean[:3].tolist(),
            "class_posterior": class_posterior(sc, belief).tolist()}


# ----------------------------------------------------------------------------- the generator

OBJECTS = ((4.0, 3.0, 0.6), (4.5, -3.0, 2.2), (10.0, 3.5, -1.4), (10.5, -3.0, 2.9), (16.0, 3.0, -2.4), (16.5, -3.5, 1.1))
OBJECT_VAR = (0.05, 0.05, 0.5e-3)
ROBOT_VAR = (1.0, 1.0, 0.04)  # a tight prior, as a known start gives
MOTION_VAR = (0.75e-3, 0.75e-3, 0.25e-3)
GEO_VAR = (0.1, 0.05)


def generate(seed: int, steps: int = 10, alpha: float = 0.25, k: float = 15.0, max_range: float = 9.0,
             fov: float = 2.0 * math.pi / 3.0, detect_p: float = 0.9, max_detections: int = 3,
             objects=OBJECTS, robot_var=ROBOT_VAR) -> dict:
    """One scenario (as JSON) of the paper's layout (Sec. V; ``objects``: another map), sampled
    from its own models: object poses and the prior mean of the start drawn from their priors, a
    1 m step with a random turn (0.15 rad), every object in view detected with probability
    ``detect_p``, at most ``max_detections`` per step in random order, scores of class 0."""
    g = np.random.default_rng(seed)
    truth = [np.array(o) + g.normal(0.0, np.sqrt(OBJECT_VAR)) for o in objects]
    start = np.zeros(3)
    prior_mean = start + g.normal(0.0, np.sqrt(robot_var))
    poses, out_steps = [start], []
    sem_chol = np.linalg.cholesky(mirror_cov(k))
    for _ in range(steps):
        action = np.array([1.0, 0.0, g.normal(0.0, 0.15)])
        x = compose(poses[-1], action)  # the true motion
        odo = compose(action, se2_exp(g.normal(0.0, np.sqrt(MOTION_VAR))))  # measured: u = a ∘ Exp(w)
        odometry = [float(v) for v in odo]
        poses.append(x)
        dets = []
        for n, o in enumerate(truth):
            r, b, view, _ = predict(x, o)
            if r <= max_range and abs(b) <= fov / 2 and g.random() < detect_p:
                z = [float(r + g.normal(0.0, math.sqrt(GEO_VAR[0]))), float(wrap(b + g.normal(0.0, math.sqrt(GEO_VAR[1]))))]
                s = mirror_means(np.asarray(view), alpha)[0] + sem_chol @ g.standard_normal(2)  # true class 0
                dets.append({"range": max(z[0], 0.0), "bearing": z[1], "scores": s.tolist(), "true_object": n})
        order = g.permutation(len(dets))[:max_detections]
        out_steps.append({"odometry": odometry, "detections": [dets[i] for i in order]})
    diag = lambda v: np.diag(v).tolist()
    return {
        "format": "hybridslam-scenario/1",
        "generator": f"scripts/numpy_reference.py generate seed={seed} steps={steps} alpha={alpha} K={k}",
        "num_classes": 2,
        "objects": [{"prior_mean": list(o), "prior_cov": diag(OBJECT_VAR), "true_pose": t.tolist(), "true_class": 0}
                    for o, t in zip(objects, truth)],
        "robot": {"prior_mean": prior_mean.tolist(), "prior_cov": diag(robot_var),
                  "true_poses": [p.tolist() for p in poses]},
        "motion_cov": diag(MOTION_VAR), "geometric_cov": diag(GEO_VAR),
        "classifier": {"model": "mirror", "alpha": alpha, "K": k},
        "sensor": {"max_range": max_range, "fov": fov},
        "steps": out_steps,
    }


def write_files(folder: str, count: int = 64, steps: int = 10, seed: int = 0) -> list[str]:
    """``count`` generated files ``ref000.json, ...`` in ``folder`` (seeds ``seed + i``); their paths."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    for i in range(count):
        paths.append(os.path.join(folder, f"ref{i:03d}.json"))
        with open(paths[-1], "w") as f:
            json.dump(generate(seed + i, steps), f)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write the benchmark's scenario files")
    g.add_argument("folder")
    g.add_argument("--count", type=int, default=64)
    g.add_argument("--steps", type=int, default=10)
    g.add_argument("--seed", type=int, default=0)
    r = sub.add_parser("run", help="run the reference filter over scenario files")
    r.add_argument("inputs", nargs="+", help="scenario files or folders of them")
    r.add_argument("--samples", type=int, default=1000)
    r.add_argument("--capacity", type=int, default=16)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("-o", "--output", default=None)
    r.add_argument("-q", "--quiet", action="store_true")
    a = parser.parse_args(argv)
    if a.cmd == "generate":
        paths = write_files(a.folder, a.count, a.steps, a.seed)
        print(f"wrote {len(paths)} files to {a.folder}")
        return 0
    t0 = time.perf_counter()
    paths = []
    for p in a.inputs:
        paths += sorted(glob.glob(os.path.join(p, "*.json"))) if os.path.isdir(p) else [p]
    out = {}
    for p in paths:
        sc = Scenario(p)
        out[p] = summary = summarize(sc, run(sc, a.samples, a.capacity, a.seed))
        if not a.quiet:
            post = " ".join(f"{row[0]:.2f}" for row in summary["class_posterior"])
            print(f"{os.path.basename(p)}: {len(summary['weights'])} components, best w {summary['weights'][0]:.3f}, "
                  f"P(class 0) {post}")
    seconds = time.perf_counter() - t0
    print(f"numpy reference: {len(paths)} file(s) in {seconds:.1f} s")
    if a.output:
        with open(a.output, "w") as f:
            json.dump({"files": out, "seconds": seconds}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
