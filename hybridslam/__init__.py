"""hybridslam: semantic localization and mapping under ambiguous data association.

Five estimators behind one interface (:class:`AbstractEstimator`): the hybrid belief of Tchuiev,
Feldman & Indelman (IROS 2019) as a fixed-capacity, jit-compiled JAX mixture (:class:`Hybrid`), and
Doherty's maximum-likelihood, Gaussian PDA, max-mixture and multimodal estimators. One driver
(:func:`run`, :func:`scan`) runs any of them on a scenario file. hybridslam computes in float64 (the
paper's variances span 1e-4 to 1e2): call :func:`setup` first, before any JAX array exists. It turns
on ``jax_enable_x64`` and sizes XLA's CPU thread pool (jaxlib 0.10.2's LAPACK kernels can deadlock on
a small one: :mod:`hybridslam.config`). Importing the package changes no process-wide setting.

Layers (each subpackage imports only from the ones before it): ``io`` (files) → ``models`` (the
generative model) → ``inference`` (Gauss-Newton, gating, ...) → ``estimators`` → ``analysis``
(metrics, marginals, errors, plots) → ``driver`` → ``studies``, ``sim``, ``planning`` → ``cli``.
"""

from .version import __version__ as __version__

from .config import setup as setup
from .config import require_x64 as require_x64

from .analysis.marginals import association_probabilities as association_probabilities
from .analysis.marginals import class_probabilities as class_probabilities
from .analysis.marginals import pose_mixture as pose_mixture
from .analysis.metrics import Metrics as Metrics
from .analysis.metrics import association_entropy as association_entropy
from .analysis.metrics import metrics as metrics
from .driver import Inputs as Inputs
from .driver import Run as Run
from .driver import Trace as Trace
from .driver import inputs_from_scenario as inputs_from_scenario
from .driver import run as run
from .driver import run_estimator as run_estimator
from .driver import scan as scan
from .studies.many import run_many as run_many
from .estimators import ESTIMATORS as ESTIMATORS
from .estimators import GPDA as GPDA
from .estimators import ML as ML
from .estimators import AbstractEstimator as AbstractEstimator
from .estimators import AbstractWeigher as AbstractWeigher
from .estimators import Hybrid as Hybrid
from .estimators import LaplaceIS as LaplaceIS
from .estimators import Linearized as Linearized
from .estimators import MaxMixture as MaxMixture
from .estimators import Mixture as Mixture
from .estimators import Multimodal as Multimodal
from .estimators import Sampled as Sampled
from .estimators import StepInfo as StepInfo
from .estimators import make_estimator as make_estimator
from .estimators import Profile as Profile
from .estimators import recommended as recommended
from .estimators.hybrid.branching import Beam as Beam
from .estimators.hybrid.branching import Exhaustive as Exhaustive
from .estimators.hybrid.weighers import make_weigher as make_weigher
from .estimators.smoothers import Filter as Filter
from .estimators.smoothers import Full as Full
from .estimators.smoothers import Incremental as Incremental
from .estimators.smoothers import Lag as Lag
from .estimators.hybrid.belief import Belief as Belief
from .estimators.hybrid.belief import Priors as Priors
from .estimators.hybrid.belief import priors_from_scenario as priors_from_scenario
from .io.result import Result as Result
from .io.result import ResultWriter as ResultWriter
from .io.result import load_result as load_result
from .io.result import save_result as save_result
from .models.scenario import Scenario as Scenario
from .io.scenario import ScenarioError as ScenarioError
from .io.scenario import load_scenario as load_scenario
from .io.scenario import save_scenario as save_scenario
from .io.scenario import stack_steps as stack_steps
from .models.classifier import ClassifierModel as ClassifierModel
from .models.classifier import Independent as Independent
from .models.classifier import Mirror as Mirror
from .models.classifier import NoClassifier as NoClassifier
from .models.registry import make_classifier as make_classifier
from .models.learned import Learned as Learned
from .models.learned import fit_classifier as fit_classifier
from .models.learned import load_classifier as load_classifier
from .models.learned import save_classifier as save_classifier
from .models.measurement import Detections as Detections
from .models.measurement import SensorModel as SensorModel
from .models.measurement import stacked_detections as stacked_detections
from .models.model import Model as Model
from .models.model import model_from_scenario as model_from_scenario
from .models.model import with_smooth_visibility as with_smooth_visibility
from .planning.gradients import best_pose_log_det as best_pose_log_det
from .planning.gradients import expected_association_entropy as expected_association_entropy
from .planning.gradients import expected_position_error as expected_position_error
from .planning.gradients import hypothesis_neg_log_weight as hypothesis_neg_log_weight
from .sim.paper import PaperSetup as PaperSetup
from .sim.paper import simulate as simulate
