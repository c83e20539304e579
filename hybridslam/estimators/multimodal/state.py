"""The multimodal estimator's static structure, traced parameters, state and per-step details
(Doherty's thesis Ch. 5; see :mod:`hybridslam.estimators.multimodal`)."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
from jaxtyping import Array, Bool, Float, Int

from ...models.model import Model
from ..smoothers.kinds import SmootherState

NAME = "multimodal"

DEFAULT_SAMPLES = 256
DEFAULT_CANDIDATES = 3
DEFAULT_MERGE_THRESHOLD = 4.0
ASSOCIATION_PRIORS = ("mc", "uniform")
PROPOSALS = ("posterior", "prior")
# jaxlib 0.10.2 on CPU splits a large batched LAPACK call (Cholesky, triangular solve, QR) across
# XLA's intra-op thread pool and blocks a pool thread waiting for it; two such calls running at once
# on a small pool deadlock (seen here: 128 Cholesky factors of 21×21 on 2 cores). Batches of D×D
# work therefore go through lax.map in chunks this small (16 factors of 93×93 were still safe).
LAPACK_CHUNK = 16
SMALL_LAPACK_BATCH = 256  # the same for the 2×2 … 12×12 matrices of gating, screening and sampling


def _chunked(fn, *args, batch_size: int = LAPACK_CHUNK):
    """``jax.vmap(fn)(*args)`` evaluated ``batch_size`` rows at a time (see ``LAPACK_CHUNK``)."""
    return jax.lax.map(lambda a: fn(*a), args, batch_size=batch_size)


@dataclasses.dataclass(frozen=True)
class Structure:
    """What the :class:`Multimodal` settings and the scenario fix about a state (static: each fixes a
    shape or a code path), resolved once by :meth:`Multimodal.init`."""

    capacity: int  # K components
    max_objects: int  # Nmax object slots
    max_detections: int  # Dmax detection slots per step
    max_steps: int  # T, length of the association history
    num_samples: int  # S Monte Carlo draws per component (Eq. 5.10)
    candidates: int  # G gated objects per detection (plus the null hypothesis)
    children: int  # C children that get a Gauss-Newton update
    gn_max_steps: int
    discovery: bool  # whether the null / new-object hypothesis exists
    association_prior: str  # "mc" (thesis Eq. 5.11) or "uniform"
    proposal: str  # "posterior" (importance sampling) or "prior" (Eq. 5.10 as written)
    beam: int | None = None  # joint assignments kept per component while they are built (None: all)
    clutter: bool = False  # a known map's null choice is a clutter detection (scored), not a skip


class Params(eqx.Module):
    """Traced parameters: changing them never recompiles."""

    new_object_log_density: Float[Array, ""]
    orientation_var: Float[Array, ""]
    merge_threshold: Float[Array, ""]
    clutter_log_density: Float[Array, ""]  # used where Structure.clutter
    new_landmark_tau: Float[Array, ""]  # τ of new_landmark="mahalanobis:TAU" (inf: the "density" rule)


class State(eqx.Module):
    """The mixture of joint Gaussians over ``[x_k, o_0..o_{Nmax-1}]`` (see the module docstring)."""

    log_weights: Float[Array, " K"]  # -inf marks an empty slot
    mean: Float[Array, "K D"]
    cov: Float[Array, "K D D"]
    class_log_probs: Float[Array, "K Nmax M"]  # log p(c_n | Z), normalized per object
    observed: Bool[Array, "K Nmax"]  # associated at least once in this component
    num_created: Int[Array, " K"]  # object slots in use (prior objects included)
    history: Int[Array, "K T Dmax"]
    k: Int[Array, ""]
    model: Model
    params: Params
    config: Structure = eqx.field(static=True)
    # What the smoother keeps (smoother=Full() or Lag(L)): each component's trajectory x_0..x_T, the
    # data so far, with Lag(L) each component's window prior; empty under Filter().
    smoothing: SmootherState = SmootherState()


class Details(eqx.Module):
    """The multimodal estimator's own diagnostics of one step (``StepInfo.details``), over the ``C``
    children that were updated."""

    parent: Int[Array, " C"]  # the component each child came from
    assoc_objects: Int[Array, "C Dmax"]  # object of each detection; -1 for an empty slot
    assoc_log_probs: Float[Array, " C"]  # log p_j of Eq. 5.9 for that object tuple; -inf infeasible
