"""Estimator settings by name: ``make_estimator(name, gate=3)`` and ``hybridslam run --gate 3``.

An estimator's options are read off its fields, so each setting is described once, beside the
field it sets:

* a field named like one of the :data:`SHARED` options (``capacity``, ``samples``, ``gate``,
  ``clutter``, ``smoother``, ``classifier``, ``gn_max_steps``, ``max_detections``,
  ``max_steps``) is that option;
* any other field is an option through its metadata,
  ``eqx.field(default=..., static=True, metadata=setting(GATE))``: the :class:`Option` (name,
  help text, command-line parser), and optionally a ``note`` that the help prints for this
  estimator (``"{default}"`` in it is the field's default), or a ``build`` that makes the
  field's value from several options (the hybrid belief's ``weights`` from ``--weights`` and
  ``--samples``);
* ``setting(show=...)`` says how :meth:`~.base.AbstractEstimator.describe` writes the field
  (``False``: not at all).

:func:`field_values` turns options into the class's keyword arguments; :func:`option_help`
writes an option's help for every estimator that takes it (``hybridslam run --help``), so a new
estimator is one module and one line in :data:`.registry.ESTIMATORS`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

from . import novelty
from .smoothers import METAVAR as SMOOTHER_METAVAR
from .smoothers import help_text as smoother_help
from .smoothers import parse_smoother

SETTING = "hybridslam.setting"  # the key of a field's metadata that holds its Setting
ANY = "*"  # Setting.notes: the note of a field's only option, whichever it is


@dataclasses.dataclass(frozen=True)
class Option:
    """One estimator setting by name: ``make_estimator(name=...)``, and ``--name`` on the command line.

    ``help``: what it means, for every estimator that takes it (each estimator's default is added
    to it); ``parse``: the command-line value's type (``None``: a flag that takes no value);
    ``convert``: what ``make_estimator`` applies to a value before it sets the field (``--smoother
    lag:50`` is ``Lag(50)``); ``none``: how the help names a field default of ``None``;
    ``default``: the default, where ``help`` already says it (the same for every estimator);
    ``command_line``: whether the commands offer it (else ``make_estimator`` only); ``described``:
    whether the result file's estimator text shows it (not the settings that only size a compiled
    step, which change no number).
    """

    name: str
    help: str
    parse: Callable[[str], Any] | None = int
    choices: tuple[str, ...] | None = None
    metavar: str | None = None
    convert: Callable[[Any], Any] | None = None
    none: str = "none"
    default: str | None = None
    command_line: bool = True
    described: bool = True

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a field's metadata says about it (:func:`setting`)."""

    options: tuple[Option, ...] = ()
    notes: Mapping[str, str] = dataclasses.field(default_factory=dict)
    build: Callable[..., Any] | None = None
    show: str | Callable[[Any], str] | bool | None = None


def setting(*options: Option, note: str | Mapping[str, str] | None = None, build: Callable[..., Any] | None = None,
            show: str | Callable[[Any], str] | bool | None = None) -> dict[str, Setting]:
    """A field's metadata: the options that set it, and how it is shown.

    ``note``: what the help says for this estimator (``"{default}"``: the field's default), one
    text or one per option name; ``build``: the field's value from the options given, as keywords
    (needed where several options set one field); ``show``: the field in the estimator text, a
    name (``"num_samples"``), a function of the estimator returning its ``name=value`` text
    (``""``: nothing), or ``False`` (never shown).
    """
    if len(options) > 1 and build is None:
        raise TypeError("setting: several options for one field need build=")
    notes = {(options[0].name if options else ANY): note} if isinstance(note, str) else dict(note or {})
    return {SETTING: Setting(tuple(options), notes, build, show)}


def clutter_density(text: str) -> float | str:
    """``--clutter``'s value (and the importers' ``--clutter-log-density``): a finite log density or ``none``."""
    if text.strip().lower() == "none":
        return "none"
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"expected a finite log density or 'none', got {text!r}")
    return value


def new_landmark_text(text: str) -> str:
    """``--new-landmark``'s value, checked (:func:`.novelty.parse_new_landmark`)."""
    novelty.parse_new_landmark("--new-landmark", text)
    return text


def _new_landmark_shown(estimator: Any) -> str:
    """The estimator text names the rule only where it is not the default (older texts stay as they were)."""
    value = getattr(estimator, "new_landmark")
    return "" if value == novelty.DENSITY else f"new_landmark={value}"


def _smoother(value: Any) -> Any:
    """``make_estimator``'s smoother: a text parsed here, a smoother (what ``--smoother`` parsed) as it is."""
    return parse_smoother(value) if isinstance(value, str) else value


CAPACITY = Option("capacity", "most components kept")
SAMPLES = Option("samples", "Monte-Carlo draws")
GATE = Option("gate", "candidate objects per detection after Mahalanobis gating", none="every object")
MAX_CHILDREN = Option(
    "max_children", "hypotheses kept while a step's associations are built; drops near the best are counted "
                    "and reported")
CLUTTER = Option(
    "clutter", "a detection may be clutter, with this log density over [range, bearing] (e.g. "
               "log(0.01 / (max_range * fov))); default: the file's sensor.clutter_log_density (written by "
               "hybridslam import), none without it; 'none': every detection is of an object",
    parse=clutter_density, metavar="{LOG_DENSITY,none}", default="file")
SMOOTHER = Option("smoother", smoother_help(), parse=parse_smoother, metavar=SMOOTHER_METAVAR, convert=_smoother)
MAX_DETECTIONS = Option("max_detections", "detection slots per step; a shared value lets files share one compiled "
                                          "step", none="the largest step", described=False)
MAX_STEPS = Option("max_steps", "history length; a shared value lets files share one compiled step",
                   none="the file's steps", described=False)
CLASSIFIER = Option("classifier", "a classifier model name or object replacing the file's", parse=str,
                    none="the file's", command_line=False)
NEW_LANDMARK = Option(
    "new_landmark", "an unknown map's rule for a new object: density (the file's new-object density competes "
                    "with the known objects) or mahalanobis:TAU (thesis Sec. 3.2.1: new only where every known "
                    "object lies beyond the squared Mahalanobis distance TAU, e.g. 9.21)",
    parse=new_landmark_text, metavar="{density,mahalanobis:TAU}", default="density")
GN_MAX_STEPS = Option("gn_max_steps", "Gauss-Newton iteration budget of an update", command_line=False)
MERGE_THRESHOLD = Option(
    "merge_threshold", "squared Mahalanobis distance below which a component merges into a likelier one with the "
                       "same objects (hybrid: and classes; their weights added; multimodal: moment-matched)",
    parse=float, none="none, as in the paper's Algorithm 1")

GATE_PROBABILITY = Option(
    "gate_probability", "probability of the chi-square gate on a detection's squared Mahalanobis distance to each "
                        "candidate object (2 degrees of freedom, thesis Sec. 3.2.1: 0.999 is d² ≤ 13.8); a detection "
                        "beyond it of every object is clutter (hybrid: on a file with clutter only)",
    parse=float, none="no chi-square gate")

_SHOWN = {"new_landmark": _new_landmark_shown}  # shared options written their own way in the estimator text
SHARED: dict[str, Option] = {o.name: o for o in (CAPACITY, SAMPLES, GATE, MAX_CHILDREN, CLUTTER, SMOOTHER,
                                                  MAX_DETECTIONS, MAX_STEPS, CLASSIFIER, GN_MAX_STEPS,
                                                  NEW_LANDMARK, MERGE_THRESHOLD, GATE_PROBABILITY)}


# --------------------------------------------------------------------------- #
# Reading a class's settings
# --------------------------------------------------------------------------- #


def field_setting(field: dataclasses.Field) -> Setting:
    """A field's :class:`Setting`: its metadata's, else the shared option of its name, else none."""
    own = field.metadata.get(SETTING)
    if own is not None and (own.options or field.name not in SHARED):
        return own
    if own is not None:  # metadata that only says how the field is shown or noted
        return dataclasses.replace(own, options=(SHARED[field.name],))
    return Setting((SHARED[field.name],), show=_SHOWN.get(field.name)) if field.name in SHARED else Setting()


def settable(cls: type) -> Iterator[tuple[dataclasses.Field, Setting]]:
    """The fields of ``cls`` that options set, with their settings, in field order."""
    for field in dataclasses.fields(cls):
        s = field_setting(field)
        if s.options:
            yield field, s


def options_of(cls: type) -> dict[str, Option]:
    """Every option ``cls`` takes, by name, in field order."""
    return {o.name: o for _, s in settable(cls) for o in s.options}


def field_values(cls: type, given: Mapping[str, Any]) -> dict[str, Any]:
    """``cls``'s keyword arguments for the options ``given`` (every one an option of ``cls``)."""
    out = {}
    for field, s in settable(cls):
        values = {o.name: (o.convert(given[o.name]) if o.convert else given[o.name])
                  for o in s.options if o.name in given}
        if values:
            out[field.name] = s.build(**values) if s.build is not None else values[s.options[0].name]
    return out


def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def value_text(value: Any) -> str:
    """A setting's value in words: a strategy's ``name``, ``%g`` for a float, else ``str``."""
    if hasattr(value, "name") and isinstance(getattr(value, "name"), str):
        return value.name
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _note(option: Option, field: dataclasses.Field, s: Setting) -> str:
    """What the help says about ``option`` for one estimator."""
    default = _default(field)
    shown = option.none if default is None else value_text(default)
    note = s.notes.get(option.name, s.notes.get(ANY))
    if note is not None:
        return note.format(default=shown)
    if option.parse is None or option.default is not None:  # a flag, or a default the help already says
        return ""
    return f"default {shown}"


def option_help(option: Option, estimators: Mapping[str, type], default: str | None = None) -> str:
    """``option``'s help: its meaning, then what it is for each estimator that takes it, grouped
    (``default``: a default to name instead of the estimators' own, e.g. a command's)."""
    groups: dict[str, list[str]] = {}
    for name, cls in estimators.items():
        for field, s in settable(cls):
            if option in s.options:
                note = _note(option, field, s) if default is None else f"default {default}"
                groups.setdefault(note, []).append(name)
    users = [n for names in groups.values() for n in names]
    if len(groups) == 1 and len(users) < len(estimators):
        (note,) = groups
        return f"{', '.join(users)}: {option.help}" + (f" ({note})" if note else "")
    parts = [note if len(groups) == 1 else f"{', '.join(names)}: {note}" for note, names in groups.items() if note]
    return option.help + (f" ({'; '.join(parts)})" if parts else "")


def all_options(estimators: Mapping[str, type]) -> dict[str, Option]:
    """Every option of the ``estimators``, by name (a ``TypeError`` where two differ under one name)."""
    out: dict[str, Option] = {}
    owner: dict[str, str] = {}
    for name, cls in estimators.items():
        for option in options_of(cls).values():
            if option.name in out and out[option.name] != option:
                raise TypeError(f"option {option.flag}: defined differently by {owner[option.name]} and {name}")
            out.setdefault(option.name, option)
            owner.setdefault(option.name, name)
    return out


# --------------------------------------------------------------------------- #
# The estimator text
# --------------------------------------------------------------------------- #


def _renamed(key: str, name: str, estimator: Any) -> str:
    return f"{key}={value_text(getattr(estimator, name))}"


def shown(estimator: Any, order: Sequence[str] | None) -> list[tuple[str, Callable[[Any], str] | None]]:
    """The fields of the estimator text in order, each with its own way of writing itself (``None``:
    ``name=value``; the caller writes ``classifier`` and ``clutter``)."""
    fields = {f.name: f for f in dataclasses.fields(estimator)}
    names = order if order is not None else [n for n in fields if n != "classifier"]
    out: list[tuple[str, Callable[[Any], str] | None]] = []
    for name in names:
        s = field_setting(fields[name])
        if s.show is False or (order is None and any(not o.described for o in s.options)):
            continue
        if isinstance(s.show, str):
            out.append((name, functools.partial(_renamed, s.show, name)))
        elif callable(s.show):
            out.append((name, s.show))
        else:
            out.append((name, None))
    return out


__all__ = ["CAPACITY", "CLASSIFIER", "CLUTTER", "GATE", "GN_MAX_STEPS", "MAX_CHILDREN", "MAX_DETECTIONS", "MAX_STEPS",
           "MERGE_THRESHOLD", "NEW_LANDMARK", "SAMPLES", "SHARED", "SMOOTHER", "Option", "Setting", "all_options", "clutter_density", "field_values",
           "option_help", "options_of", "setting", "value_text"]
