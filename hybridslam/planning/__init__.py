"""Belief-space planning on the hybrid belief (DA-BSP): candidate scoring, gradient refinement of an
action sequence, and the differentiable objectives of :mod:`.gradients`."""

from .plan import CHUNK as CHUNK
from .plan import PLAN_AXIS as PLAN_AXIS
from .plan import Plan as Plan
from .plan import Refined as Refined
from .plan import World as World
from .plan import arc_candidates as arc_candidates
from .plan import expected_objective as expected_objective
from .plan import objective as objective
from .plan import observe as observe
from .plan import predict_observations as predict_observations
from .plan import prepare as prepare
from .plan import refine_actions as refine_actions
from .plan import rollout as rollout
from .plan import sample_world as sample_world
from .plan import score_candidates as score_candidates
from .plan import turn_actions as turn_actions
