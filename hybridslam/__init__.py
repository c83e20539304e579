"""hybridslam: semantic localization and mapping under ambiguous data association.

The hybrid belief of Tchuiev, Feldman & Indelman (IROS 2019) as a fixed-capacity, jit-compiled JAX
mixture. hybridslam computes in float64: importing it turns on ``jax_enable_x64``, because the
paper's variances span 1e-4 to 1e2 (README, "Numerics").
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

from .belief import Belief as Belief
from .belief import Config as Config
from .belief import Detections as Detections
from .belief import Priors as Priors
from .belief import init_belief as _init_belief_from_priors
from .belief import priors_from_scenario as priors_from_scenario
from .belief import stacked_detections as stacked_detections
from .classifier import ClassifierModel as ClassifierModel
from .classifier import Independent as Independent
from .classifier import Mirror as Mirror
from .classifier import NoClassifier as NoClassifier
from .classifier import make_classifier as make_classifier
from .gradients import best_pose_log_det as best_pose_log_det
from .gradients import expected_association_entropy as expected_association_entropy
from .gradients import expected_position_error as expected_position_error
from .gradients import hypothesis_neg_log_weight as hypothesis_neg_log_weight
from .gradients import rollout as rollout
from .learned import Learned as Learned
from .learned import fit_classifier as fit_classifier
from .learned import load_classifier as load_classifier
from .learned import save_classifier as save_classifier
from .marginals import association_probabilities as association_probabilities
from .marginals import class_probabilities as class_probabilities
from .marginals import pose_mixture as pose_mixture
from .measurement import SensorModel as SensorModel
from .metrics import Metrics as Metrics
from .metrics import association_entropy as association_entropy
from .metrics import metrics as metrics
from .model import Model as Model
from .model import model_from_scenario as model_from_scenario
from .model import with_smooth_visibility as with_smooth_visibility
from .result import Result as Result
from .result import load_result as load_result
from .result import save_result as save_result
from .run import run_scenario as run_scenario
from .scenario import Scenario as Scenario
from .scenario import ScenarioError as ScenarioError
from .scenario import load_scenario as load_scenario
from .scenario import save_scenario as save_scenario
from .scenario import stack_steps as stack_steps
from .simulate import PaperSetup as PaperSetup
from .simulate import simulate as simulate
from .step import StepInfo as StepInfo
from .step import step as step


def init_belief(
    source: "Scenario | Priors",
    model: "Model | None" = None,
    config: "Config | None" = None,
    **settings,
) -> Belief:
    """The initial belief (one component, every class open) from a scenario or explicit priors.

    ``init_belief(scenario)`` reads priors and model from the file and sizes the config for it;
    ``init_belief(priors, model, config)`` builds it from parts. ``settings`` (``capacity``,
    ``num_samples``, ``weights``, ...) fill a :class:`Config` when none is given.
    """
    from .run import config_for

    if isinstance(source, Scenario):
        model = model_from_scenario(source) if model is None else model
        config = config_for(source, **settings) if config is None else config
        source = priors_from_scenario(source)
    elif model is None:
        raise TypeError("init_belief(priors, model, config): a model is required with explicit priors")
    return _init_belief_from_priors(source, model, Config(**settings) if config is None else config)
