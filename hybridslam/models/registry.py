"""Classifier models by name: the ``classifier.model`` of a scenario file (SCENARIO_FORMAT.md).

Its own module because ``"learned"`` needs :mod:`.learned`, which builds on :mod:`.classifier`.
"""

from __future__ import annotations

from jaxtyping import ArrayLike, Float

from .classifier import ClassifierModel, Confusion, Independent, Mirror, NoClassifier
from .learned import load_classifier

MODELS = ("mirror", "independent", "none", "learned", "confusion")


def make_classifier(
    name: str, num_classes: int, alpha: float | None = None, K: float | None = None, *,
    path: str | None = None, matrix: Float[ArrayLike, "M M"] | None = None,
) -> ClassifierModel:
    """Build a classifier model by its scenario-file name (``classifier.model``).

    ``"learned"`` loads the model file at ``path`` (:func:`hybridslam.learned.load_classifier`);
    ``"confusion"`` takes the ``num_classes`` × ``num_classes`` ``matrix`` (``matrix[label, class]``).
    """
    if name in ("mirror", "independent"):
        if alpha is None or K is None:
            raise ValueError(f"classifier: the {name!r} model needs alpha and K")
        # equinox: Mirror and Independent inherit _AlphaK's __init__ (mypy sees the field order)
        return (Mirror if name == "mirror" else Independent)(alpha, K)  # type: ignore[call-arg, arg-type]
    if name == "none":
        return NoClassifier(num_classes)
    if name == "learned":
        if path is None:
            raise ValueError("classifier.path: the 'learned' model needs the path of its model file")
        try:
            model = load_classifier(path)
        except ValueError as e:
            raise ValueError(f"classifier.path: {e}") from e
        if model.num_classes != num_classes:
            raise ValueError(
                f"classifier.path: {path!r} is a model of {model.num_classes} classes, expected {num_classes}"
            )
        return model
    if name == "confusion":
        if matrix is None:
            raise ValueError("classifier.matrix: the 'confusion' model needs its confusion matrix")
        confusion = Confusion(matrix)
        if confusion.num_classes != num_classes:
            raise ValueError(
                f"classifier.matrix: a {confusion.num_classes}-class matrix, expected {num_classes} classes")
        return confusion
    raise ValueError(f"classifier.model: unknown model {name!r} (known: {', '.join(MODELS)})")
