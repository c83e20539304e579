"""Estimators: five answers to ambiguous data association behind one interface (:mod:`.base`).

* :class:`Hybrid` (``hybrid``) — the hybrid belief of Tchuiev, Feldman & Indelman (IROS 2019).
* :class:`ML` (``ml``) — maximum-likelihood association (Doherty's thesis Sec. 3.3).
* :class:`GPDA` (``gpda``) — Gaussian probabilistic data association (Sec. 3.4).
* :class:`MaxMixture` (``max-mixture``) — max-mixtures semantic SLAM (Ch. 4).
* :class:`Multimodal` (``multimodal``) — sum-mixture (multimodal) semantic SLAM (Ch. 5).

Each is an ``equinox.Module`` whose fields are its settings; :func:`make_estimator` builds one from
its name and command-line style options; :func:`hybridslam.driver.run` runs any of them.
"""

from .base import AbstractEstimator as AbstractEstimator
from .base import Mixture as Mixture
from .base import StepInfo as StepInfo
from .gpda import GPDA as GPDA
from .hybrid.estimator import Hybrid as Hybrid
from .hybrid.weighers import AbstractWeigher as AbstractWeigher
from .hybrid.weighers import LaplaceIS as LaplaceIS
from .hybrid.weighers import Linearized as Linearized
from .hybrid.weighers import Sampled as Sampled
from .maxmix import MaxMixture as MaxMixture
from .ml import ML as ML
from .multimodal import Multimodal as Multimodal
from .registry import ESTIMATORS as ESTIMATORS
from .registry import make_estimator as make_estimator
from .profiles import Profile as Profile
from .profiles import recommended as recommended
