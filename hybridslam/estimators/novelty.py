"""When a detection may be a new landmark: the rule every estimator reads on an unknown map.

Two rules (the estimators' ``new_landmark`` setting):

* ``"density"`` (the default): "new" is one more association hypothesis, scored by the scenario's
  ``discovery.new_object_log_density`` (the null term of thesis Eq. 4.13) beside each known object's
  ``N(z; h, S)``; the association decides. Far from the truth a well-predicted old landmark may
  lose to "new" (a known object loses beyond ``d² ≈ 2 (log N(0; S) − log ρ_new)``).
* ``"mahalanobis:TAU"`` (thesis Sec. 3.2.1, Measurement Gating): a detection is a new landmark only
  when every known one lies beyond the threshold ``τ`` on the squared Mahalanobis distance
  ``d² = rᵀ S⁻¹ r`` of its innovation (Eq. 4.15's ``S``); otherwise it is associated with a known
  one. ``TAU`` is a value of ``d²`` (2 degrees of freedom: ``−2 log(1 − p)`` is the ``p`` quantile,
  e.g. 9.21 for 99%, 13.8 for 99.9%). ``ml``, ``gpda``, ``max-mixture`` and ``multimodal`` also drop
  the known candidates beyond ``τ`` (τ is their gate where it is the narrower), so a detection with
  none inside is new for certain, as in the thesis. The hybrid belief keeps its candidates (its
  point is to carry the alternatives): "new" is a hypothesis only where no known object lies inside
  ``τ``, and there it competes by the density as before. Where no assignment of a step can keep the
  rule (two detections whose only object inside ``τ`` is the same one) the assignments that break
  it fewest times compete, so a step is never left without a hypothesis.

The new hypothesis's weight is the density under both rules: the rule decides which hypotheses
exist, not how much "new" weighs against them where it exists.

In a state the rule is one traced number, :func:`threshold`: ``τ``, or ``inf`` for the density rule,
under which the primitives below change nothing. Every rule and ``τ`` then share one compiled step.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

DENSITY = "density"
MAHALANOBIS = "mahalanobis"


def parse_new_landmark(owner: str, value: object) -> float | None:
    """``value`` checked: ``None`` for ``"density"``, ``τ`` for ``"mahalanobis:TAU"`` (``τ > 0``, finite).
    Raises ``ValueError`` naming ``owner.new_landmark``."""
    if value == DENSITY:
        return None
    if isinstance(value, str) and value.startswith(MAHALANOBIS + ":"):
        try:
            tau = float(value.split(":", 1)[1])
        except ValueError:
            tau = math.nan
        if math.isfinite(tau) and tau > 0:
            return tau
    raise ValueError(f"{owner}.new_landmark: expected 'density' or 'mahalanobis:TAU' with TAU a positive number "
                     f"(a squared Mahalanobis distance, e.g. 'mahalanobis:9.21'), got {value!r}")


def threshold(owner: str, value: object) -> float:
    """The rule as the state's traced number: ``τ`` of ``"mahalanobis:TAU"``, ``inf`` for ``"density"``
    (checked as :func:`parse_new_landmark` does)."""
    tau = parse_new_landmark(owner, value)
    return math.inf if tau is None else tau


def allowed(d2: Float[Array, "..."], tau: float | Float[Array, ""]) -> Bool[Array, "..."]:
    """Where an object may be associated under the rule: within ``d² <= τ``; everywhere under the
    density rule (``τ = inf``, whatever ``d2`` holds)."""
    return (d2 <= tau) | ~jnp.isfinite(tau)


def known_within(d2: Float[Array, "Dmax N"], num_created: Int[Array, ""] | None,
                 tau: float | Float[Array, ""]) -> Bool[Array, " Dmax"]:
    """Per detection, whether some created object (index ``< num_created``; all if ``None``) lies
    within ``d² <= τ``: where the Mahalanobis rule rules "new" out (nowhere under the density rule)."""
    inside = d2 <= tau
    if num_created is not None:
        inside &= jnp.arange(d2.shape[1])[None, :] < num_created
    return jnp.any(inside, axis=-1) & jnp.isfinite(tau)


def restrict(cand: Int[Array, "Dmax G"], d2: Float[Array, "Dmax N"], tau: float | Float[Array, ""]
             ) -> tuple[Int[Array, "Dmax G"], Bool[Array, " Dmax"]]:
    """The Mahalanobis rule on a gate of ``G`` objects per detection (``-1``: none): the candidates
    beyond ``τ`` dropped (``-1``), and per detection whether one is left (then "new" breaks the rule;
    under the density rule every candidate stays and "new" breaks nothing).
    ``d2``: every object's squared Mahalanobis distance to each detection."""
    d2_cand = jnp.take_along_axis(d2, jnp.maximum(cand, 0), axis=1)
    cand = jnp.where((cand >= 0) & allowed(d2_cand, tau), cand, -1)
    return cand, jnp.any(cand >= 0, axis=-1) & jnp.isfinite(tau)
