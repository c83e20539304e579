"""Association strategies, each a full estimator with one interface (see :mod:`.base`).

* ``hybrid`` — the hybrid belief of Tchuiev, Feldman & Indelman (IROS 2019): :mod:`hybridslam.step`.
* ``ml`` — maximum-likelihood association (Doherty's thesis Sec. 3.3).
* ``gpda`` — Gaussian probabilistic data association (Sec. 3.4).
* ``max-mixture`` — max-mixtures semantic SLAM (Ch. 4).
* ``multimodal`` — sum-mixture (multimodal) semantic SLAM (Ch. 5).

``run_estimator(scenario, name, ...)`` runs any of them and returns the result file's content.
"""

from .base import ESTIMATORS as ESTIMATORS
from .base import Mixture as Mixture
from .base import Settings as Settings
from .base import get_estimator as get_estimator
from .base import run_estimator as run_estimator
