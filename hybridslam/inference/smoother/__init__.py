"""A factor-graph smoother: the whole trajectory and the map re-solved by damped Gauss-Newton.

The filters of :mod:`hybridslam.estimators` keep one joint Gaussian over ``[x_k, objects]``; the
papers' estimators smooth: every step re-solves (relinearizes) the trajectory ``x_0..x_T`` and the
objects, like GTSAM's batch Levenberg-Marquardt or iSAM2. This package is that solver for one
component; batch components with ``jax.vmap``. Its modules: :mod:`.graph` (the factors),
:mod:`.linearization` (``H`` and ``g`` in blocks), :mod:`.blocks` (3×3 and block-tridiagonal algebra),
:mod:`.elimination` (the elimination orders, as objects), :mod:`.lm` (the Levenberg-Marquardt loop,
its state and its termination config), :mod:`.implicit` (:func:`solve` and its derivative) and
:mod:`.marginals`.

**The problem.** Variables: ``P`` poses ``X (P, 3)`` and ``N`` objects ``O (N, 3)`` (``[x, y, θ]``).
The negative log posterior (up to a constant) is ``½‖r(X, O)‖²`` with whitened residuals

* a dense Gaussian prior on ``y₀ = [x_0, o_0, .., o_{N-1}]``: ``R (y₀ ⊖ μ)`` (headings wrapped),
  ``Λ = RᵀR``. Dense because a fixed-lag window's marginalized prior couples ``x_0`` and the map;
* odometry ``W Log(u_i⁻¹ ∘ x_{i-1}⁻¹ ∘ x_i)`` (:func:`~hybridslam.motion.odometry_residual`,
  GTSAM's ``BetweenFactor<Pose2>``), ``i = 1..P-1``;
* measurement factors ``f`` between pose ``meas_pose[f]`` and candidates ``meas_objects[f, g]``
  with log-weights ``log w_fg`` and a whitened residual ``r_fg, log η_fg = residual_fn(x, o, data_f, g)``
  (``log p = log η − ½‖r‖²``; the measurement factor of Eq. 10). ``mode="sum"``: every candidate
  is a factor ``√w_fg r_fg`` (ML and hybrid: ``G = 1``, ``w = 1``; Gaussian PDA: ``w = p_fg``).
  ``mode="max"``: a max-mixture (Olson & Agarwal; Doherty thesis Sec. 4.1.1, Eq. 4.16): at every
  iterate the factor is its active component ``g* = argmin_g ½‖r_g‖² − log η_g − log w_g`` over
  the candidates and the null component (cost ``−log w_null``, no residual), with no gradient
  through the choice.

**Gauss-Newton** (the update of Tchuiev et al. Eq. 9-11, over the whole trajectory): at an iterate
``y`` with stacked Jacobian ``J``, the step solves ``(JᵀJ + λD) δ = −Jᵀr`` and ``y ← y ⊕ δ``. The
retraction ``⊕`` is plain vector addition on ``[x, y, θ]`` with the heading wrapped (what the
filters do; the minimizer does not depend on the retraction, only the path does).

**Structure.** ``H = JᵀJ`` is never formed from a dense Jacobian: each factor's Jacobian (3×3,
6×6 blocks by ``jax.jacfwd``, vmapped over factors) is scatter-added into

* a block-tridiagonal pose part (odometry chain; measurement factors add to diagonal blocks),
* a pose-object part ``B (3P, 3N)`` (one 3×3 block per measurement factor, plus the prior's
  ``x_0``-map coupling),
* an object part ``C (3N, 3N)``: the prior's ``Λ_OO`` plus 3×3 diagonal blocks.

The elimination ``method="poses-first"`` (:class:`~.elimination.PosesFirst`; the default unless there are more objects than poses
or few poses, :func:`resolve_method`) eliminates the poses first: one block
Cholesky of the tridiagonal pose part (a ``lax.scan`` with closed-form 3×3 Cholesky factors,
elementwise so it fuses on CPU) solves ``A X = [B | −g_p]`` for all right-hand sides at once; the
Schur complement ``S = C − Bᵀ A⁻¹ B`` onto the objects is one dense matmul and a dense ``3N``
Cholesky; back-substitution is ``δ_p = A⁻¹(−g_p) − (A⁻¹B) δ_o``. ``"objects-first"`` (``C``
inverted, then a dense ``3P`` pose system) and ``"dense"`` (the full ``H``, ``jnp.linalg.solve``:
the reference) are selectable; see ``scripts/bench_smoother.py`` for timings. When the prior couples
no two objects (``FactorGraph.independent_objects``: every run's prior is so, a fixed-lag window's
is not), ``C`` is block-diagonal and objects-first inverts it block by block, in closed form: the
hallway's step (61 poses, 70 object slots) then costs one ``3P`` Schur product and Cholesky instead
of two dense ``3N`` factorizations besides.

**Live prefix.** A run's graph is padded to the whole trajectory and the map's capacity; after ``k``
steps only ``x_0..x_k`` and the objects created so far are active, and the padded slots after them
are uncoupled identity rows. :func:`linearize` records those prefixes (``Linearization.live_poses``,
``live_objects``), and :func:`solve_normal` and :func:`marginal` eliminate only the smallest of four
compiled sizes that holds them (:mod:`.buckets`: a quarter, half, three quarters or all of each axis
of 32 slots or more), with the same result: the hallway's solves early in a run work on 16 of its 61
poses and 18 of its 70 objects. Four sizes cost 2-6 s more compilation on the hallway and MRCLAM
(``HYBRIDSLAM_BUCKETS=1``: one size, the whole graph).

**Damping.** Levenberg-Marquardt with Marquardt's scaling ``D = diag(H)`` (clipped to
``[1e-6, 1e32]`` like Ceres, so an unobserved direction is still damped) and Nielsen's update of
``λ`` from the gain ratio ``ρ = (F(y) − F(y ⊕ δ)) / (L(0) − L(δ))``: accept if the true cost
decreased, then ``λ ← λ max(1/3, 1 − (2ρ − 1)³)``; else ``λ ← λν``, ``ν ← 2ν``. The loop keeps the
linearization of the current iterate: each iteration linearizes once, at the candidate (its cost
comes with it). Stops when ``max|δ| < state_tol`` (1 µm / 1 µrad by default, the filters'
``GN_TOLERANCE``), when an accepted step lowers the cost by less than ``cost_rtol`` relative, when
the gain still to come, estimated from the observed rate, is below ``cost_atol`` (below), when the
step just taken was (nearly, ``λ ≤ 1e-3``) Gauss-Newton's and its model gain ``L(0) − L(δ)`` is
below ``cost_atol`` (the Newton decrement test: the quadratic model has less than that left to
give, so the step is kept if it lowered the cost and nothing more is tried), or after
``max_steps`` iterations. The decrement test is what ends a warm-started solve: from the previous
step's trajectory a hallway solve reached gains ``0.47, 2e-4, 4e-7, 1e-8, 1e-10`` nats and used to
take one more iterate to see the relative test pass. (The estimators' smoother steps pass a looser
``cost_atol`` before a scenario's last step, :class:`~hybridslam.estimators.smoothers.kinds.Full`'s
``step_atol``: the second of those iterates ends such a solve.)

**Linear convergence.** Gauss-Newton converges quadratically only on zero-residual problems. The
viewpoint-dependent semantic factors at ``alpha = 0.5`` (Eq. 18) are not: their second-order term,
which Gauss-Newton leaves out, is about a third of the Hessian in some direction, and the cost then
falls by a constant factor ``r ≈ 1/3`` per iterate (measured on the default study's tracks), so a
relative test of ``1e-12`` takes 15-25 iterates. Accepted steps with gains ``a_{n-1}, a_n`` give
the rate ``r_n = a_n / a_{n-1}``; when the rate is steady (``r_n`` in ``[0.05, 0.9]`` and within a
factor 2 of ``r_{n-1}``: linear convergence, not the collapsing rates of a quadratic endgame or of a
shrinking damping, which the relative test handles), the gain still to come is the geometric
series ``a_n r_n / (1 − r_n)``, and the solve stops when that is below ``cost_atol`` (``1e-9``
nats: the mode is then within ``√(2·1e-9) ≈ 5e-5`` standard deviations of the optimum) while
``λ ≤ 1`` (a step at least half Gauss-Newton's).

**Why not optimistix.** ``optx.AbstractGaussNewton`` hands its descent the Jacobian as a lineax
operator of the flattened residual function (``jax.linearize`` of the whole residual vector) and
the descent's ``query`` gets no ``args``. A structured descent would have to carry the graph
inside the solver object and re-linearize it blockwise next to optimistix's own linearization,
and the trust-region search's predicted reduction would go through the full-residual JVP again.
The hand-written ``lax.while_loop`` linearizes once per iteration, shares its blocks with
:func:`marginal` and :func:`marginalize_first`, and still reports an ``optx.RESULTS``.

**Inactive variables** (``pose_active``, ``object_active``; padded slots) carry no factors; their
rows of ``H`` become the identity and their gradient zero, so they stay exactly at their initial
value and every factorization stays finite.

**Derivatives.** :func:`solve` is differentiable (``jax.grad``, ``jax.jacfwd``, ``jax.vmap`` of
them) with respect to every floating-point input of the graph: odometry, measurements, noise
square roots, prior, candidate weights. Not through the ``lax.while_loop`` (reverse mode cannot
go through one, and the iterations are not the function): the solution ``y*`` satisfies
``g(y*, θ) = Jᵀr = 0``, so by the implicit function theorem ``(∂g/∂y) ẏ = −(∂g/∂θ) θ̇``
(a ``jax.custom_jvp`` rule, :func:`_solve_jvp`; optimistix's ``ImplicitAdjoint`` does the same for
its own solvers). ``∂g/∂y`` is the exact Hessian, applied by forward-mode products, and the system
is solved by conjugate gradients (``lineax``) preconditioned with the solution's own Gauss-Newton
factorization, the same structured elimination as a step: the two differ only by the residuals'
second-order terms, so a few iterations suffice. The solution's linearization, which
:func:`marginal` turns into the covariance, is differentiated at ``(y*, θ)`` with ``ẏ``, so the
smoothed marginals have exact derivatives too. Exact at the optimum; a solve stopped early (the
estimators' loose tolerance before a scenario's last step) gives the derivative at the point it
stopped. Discrete choices (the max-mixture's active components) are held fixed. Costs nothing
unless differentiated.
"""

from .blocks import tridiagonal_solve as tridiagonal_solve
from .elimination import SMALL_POSE_SYSTEM as SMALL_POSE_SYSTEM
from .elimination import AbstractElimination as AbstractElimination
from .elimination import Auto as Auto
from .elimination import Dense as Dense
from .elimination import Method as Method
from .elimination import ObjectsFirst as ObjectsFirst
from .elimination import PosesFirst as PosesFirst
from .elimination import as_elimination as as_elimination
from .elimination import resolve_method as resolve_method
from .elimination import solve_normal as solve_normal
from .graph import DetectionData as DetectionData
from .graph import FactorGraph as FactorGraph
from .graph import Mode as Mode
from .graph import RangeBearingResidual as RangeBearingResidual
from .graph import SensorResidual as SensorResidual
from .graph import check_shapes as check_shapes
from .implicit import solve as solve
from .linearization import Linearization as Linearization
from .linearization import linearize as linearize
from .linearization import prior_information as prior_information
from .lm import Solution as Solution
from .lm import TerminationConfig as TerminationConfig
from .lm import levenberg_marquardt as levenberg_marquardt
from .lm import retract as retract
from .marginals import Covariances as Covariances
from .marginals import covariances as covariances
from .marginals import first_pose_factors as first_pose_factors
from .marginals import marginal as marginal
from .marginals import marginalize_first as marginalize_first
from .marginals import marginalize_first_information as marginalize_first_information
