"""Multimodal (sum-mixture, non-Gaussian) semantic SLAM: Doherty's thesis Ch. 5, smoothed or filtered.

The thesis marginalizes each step's association out of the factor graph (Eq. 5.3-5.7) and keeps
the resulting *sum*-mixture factors (Eq. 5.11), weighted by association probabilities that are
estimated by Monte Carlo over pose samples with joint compatibility (Eq. 5.9-5.10); mm-iSAM then
solves the non-Gaussian factor graph with nonparametric belief propagation.

Representation (why a Gaussian sum, not evenly weighted kernels). The belief at step ``k`` is a
fixed-capacity mixture of ``K`` weighted joint Gaussians over
``[x_k, o_0, ..., o_{Nmax-1}]`` (object slots and their creation as in :mod:`hybridslam.discovery`),
each with its own association history ``β_1:k``, number of created objects and per-object class
posterior. Given the prior mixture ``Σ_i w_i N_i`` and the step's sum-mixture factor
``f = Σ_j p_j ρ_j`` (Eq. 5.11), the posterior is exactly ``Σ_ij w_i p_j N_i ρ_j``: a child per
(component ``i``, joint assignment ``j``) with weight ``w_i p_j L_ij``, ``L_ij = ∫ N_i ρ_j``, and
Gaussian ``∝ N_i ρ_j`` found by Gauss-Newton (:func:`hybridslam.update.prior_gauss_newton`). A Gaussian
sum represents a mode with one component however unlikely it is, whereas evenly weighted kernels
(Fig. 5-2) or resampled particles (a Rao-Blackwellized particle filter) represent a mode of weight
``w`` by about ``w·K`` kernels, so a mode below ``1/K`` is lost by sampling noise alone — exactly the
late-mode failure Sec. 5.2.1 warns about. We keep the weights explicit instead.

Reduction without pruning. The children are reduced back to ``K`` by greedy moment-matching
merging (:func:`cluster`, :func:`spread`): the heaviest unclaimed child becomes a centre and claims every child within
a squared Mahalanobis distance ``merge_threshold`` that has the same number of created objects;
``K`` rounds; children left over are merged into their nearest centre. No mass is ever dropped
there, and separated modes stay separate components as long as there are at most ``K`` of them.
A child more than ``RELEVANT_NATS`` (30 nats: relative weight below 1e-13) under the best child
becomes no centre: its mass joins its nearest centre, so the belief carries no component it could
not show.
Only the ``children`` best children (a static count, ranked by the linearized likelihood below,
each named object's in-view probability included) get a Gauss-Newton update and a Monte Carlo
weight: the linearized mass of the rest is reported in ``StepInfo.dropped_mass`` and as a warning,
never silently.

Association probabilities (Eq. 5.9-5.10). ``L_ij`` integrates the joint likelihood of the step's
detections over the pose and the associated objects, ``y = [x_k, o_{d_1}, ...]``, by Monte Carlo:
``L_ij ≈ mean_s N_i(y_s) Π_k p(z_k | y_s, d_k) / q(y_s)`` with reparameterized standard-normal
draws, the same for every child (common random numbers make the children comparable). Joint
compatibility: every detection of an assignment is scored on the *same* sample. A detection of an
object scores the range-bearing density, the object observation model (0/1 footprint) and the
semantic term marginalized over the object's class posterior, ``Σ_c P(z^s | c, viewpoint)
p(c | Z^-)`` (the bracket of Eq. 5.10; the viewpoint comes from the sample, so viewpoint-dependent
classifiers are handled exactly). A "new object" choice scores ``new_object_log_density`` (the null
hypothesis of Sec. 3.2.1) times the semantic term under a uniform class prior, the new object's
unobserved orientation drawn from ``N(0, new_object_orientation_var)``; with the component's object
slots all used it is an *unmapped* object (object ``-1``: weighed the same, not stored, counted in
``StepInfo.unmapped``). ``p_j`` (Eq. 5.9) is the
total mass ``Σ w_i L_ij`` of the children that name the same object tuple, normalized over the
updated children (with one component and every assignment updated: ``L_j / Σ L``).

The proposal ``q`` (option ``proposal``): ``"prior"`` samples the component's marginal over ``y``,
which is Eq. 5.10 as written (pose and landmark samples from the belief). Its variance explodes
when the measurement is much sharper than the prior — a loop closure after drift, or any broad
prior (a 2 m prior against a 0.1 m measurement leaves ~1 useful sample in 400). The default
``"posterior"`` samples the child's Gauss-Newton (Laplace) posterior instead and importance-weights
by ``N_i / q``: the same integral, with weights that stay nearly equal. The tests check it against
brute-force quadrature.

Eq. 5.9 uses the step's detections to compute ``p_j``, and the factor of Eq. 5.11 multiplies the
likelihood ``ρ_j`` once more: the thesis's factor counts the detections twice, which sharpens the
association weights (``association_prior="mc"``, the default, follows the thesis). With
``association_prior="uniform"`` the children are weighted ``w_i L_ij``, the exact Bayes posterior
under a uniform prior over joint assignments.

Gating (Sec. 3.2.1): each detection considers the ``candidates`` created objects nearest in the
linearized Mahalanobis distance of the component's mean, plus the null / new-object hypothesis;
joint assignments are injective tuples of those choices, ranked by their linearized likelihood
(joint innovation density at the mean). By default (``max_assignments``) they are built one
detection at a time by a beam search that scores each extension by its conditional density given
the detections already assigned (:mod:`hybridslam.inference.sequential`: the same joint density,
a 2×2 term per detection); ``max_assignments=None`` enumerates every tuple and scores each at once
(the reference).

Smoothing (``smoother=Full()``, the default, or ``Lag(L)``; :mod:`..smoothers`): the children are
clustered on their filter estimates (above), then each merged component's centre has its whole
trajectory and map (or its window) relinearized with every geometric factor of its association
history, and the component is its cluster moment-matched about the centre's smoothed estimate:
members keep their filter offsets from the centre and take the centre's smoothed covariance (they
are within ``merge_threshold`` of it and created the same objects). A component keeps its centre's
trajectory. This is the static-shape stand-in for mm-iSAM: a Gaussian sum of smoothed hypotheses
where mm-iSAM propagates nonparametric beliefs through one graph. ``K`` smoothings per step, not
one per child (2·K): the used centres form a prefix, and
:func:`~hybridslam.inference.batching.map_live` skips the rest.

The continuous update uses the geometric part only: the class-marginalized semantic factor is a
mixture over classes, not a Gaussian; it enters the weights (above) and each object's class
posterior, which is updated with ``P(z^s | c, viewpoint)`` at the child's posterior mean (new
objects: averaged over their sampled orientations). ``view`` reports per component the argmax class
of every object the component has associated, ``-1`` otherwise.

Settings (:class:`Multimodal`): ``candidates`` (3), ``children`` (``2·capacity``),
``merge_threshold`` (4.0, squared Mahalanobis distance over the whole state), ``association_prior``
(``"mc"`` or ``"uniform"``), ``proposal`` (``"posterior"`` or ``"prior"``), ``samples``
(draws per child, 256), ``clutter`` (``"file"``: the scenario's ``sensor.clutter_log_density``,
none without it).

Clutter (``clutter``, a known map only; on an unknown map the null choice is a new object, and
the file's clutter density is not used): without it every detection is of an object (the
thesis's model), and the null choice of a known map leaves a detection unassociated only where no
injective assignment names them all (ranked below every full assignment, counted in ``skipped``).
With a log density over [range, bearing] the null choice is a clutter detection scored like a new
object's (:func:`_null_log_likelihood`, that density for ``new_object_log_density``; the hybrid
belief's clutter hypothesis), weighed against the assignments by the same Monte Carlo integral,
and counted in ``rejected``: spurious detections (ghosts, a duplicate, one outside every object's
footprint) are explained instead of dragging the pose or emptying the step. With clutter the
candidates are also gated (``children.CLUTTER_GATE``: the 0.999 chi-square gate of the
single-Gaussian estimators, Sec. 3.2.1): an object beyond it is no candidate, and a detection with
none is clutter (on MRCLAM, dataset 6, robot 2, unfiltered: 0.235 → 0.155 m smoothed APE).
"""

from .state import ASSOCIATION_PRIORS as ASSOCIATION_PRIORS
from .state import DEFAULT_CANDIDATES as DEFAULT_CANDIDATES
from .state import DEFAULT_MERGE_THRESHOLD as DEFAULT_MERGE_THRESHOLD
from .state import DEFAULT_SAMPLES as DEFAULT_SAMPLES
from .state import Details as Details
from .state import LAPACK_CHUNK as LAPACK_CHUNK
from .state import NAME as NAME
from .state import Params as Params
from .state import PROPOSALS as PROPOSALS
from .state import SMALL_LAPACK_BATCH as SMALL_LAPACK_BATCH
from .state import State as State
from .state import Structure as Structure
from .likelihood import assignment_objects as assignment_objects
from .likelihood import class_log_likelihoods as class_log_likelihoods
from .likelihood import condition as condition
from .likelihood import draws as draws
from .likelihood import gate as gate
from .likelihood import joint_log_likelihood as joint_log_likelihood
from .likelihood import localized_terms as localized_terms
from .likelihood import sampled_log_likelihood as sampled_log_likelihood
from .likelihood import screen_log_likelihood as screen_log_likelihood
from .likelihood import semantic_log_marginal as semantic_log_marginal
from .likelihood import skipped_detections as skipped_detections
from .likelihood import slot_log_likelihood as slot_log_likelihood
from .likelihood import slot_terms as slot_terms
from .likelihood import SlotTerms as SlotTerms
from .likelihood import sub_gaussian as sub_gaussian
from .likelihood import tuple_log_probs as tuple_log_probs
from .children import association_log_probabilities as association_log_probabilities
from .children import Children as Children
from .children import finish_child as finish_child
from .children import gauss_newton_child as gauss_newton_child
from .children import hypotheses as hypotheses
from .clustering import cluster as cluster
from .clustering import clustered as clustered
from .clustering import spread as spread
from .estimator import Multimodal as Multimodal
