"""One place to register an estimator: its options read off its fields (``hybridslam.estimators.options``),
the commands' flags and help written from them, its estimator text derived from them.

No estimator runs here (no compile): the tests build estimators and parsers only.
"""

from __future__ import annotations

import argparse
from typing import ClassVar

import equinox as eqx
import pytest

import hybridslam as hs
from hybridslam import cli
from hybridslam.cli.common import estimator_from_args
from hybridslam.estimators import registry
from hybridslam.estimators.options import Option, all_options, option_help, options_of, setting

BOOST = Option("boost", "how far the toy turns its gate up")


class Toy(hs.ML):
    """A toy estimator: maximum-likelihood association with one setting of its own."""

    boost: int = eqx.field(default=2, static=True, metadata=setting(BOOST))

    name: ClassVar[str] = "toy"
    title: ClassVar[str] = "a toy"
    reference: ClassVar[str] = "tests/test_registry.py"
    described = None  # every field, in field order


def _actions(parser: argparse.ArgumentParser, command: str) -> dict[str, argparse.Action]:
    """The options of one subcommand, by flag."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {flag: a for a in sub._actions for flag in a.option_strings}


def test_a_registered_estimator_is_offered_with_its_options(monkeypatch):
    monkeypatch.setitem(registry.ESTIMATORS, "toy", Toy)  # the one line that registers it
    parser = cli.build_parser()
    for command in ("run", "demo", "sweep"):
        actions = _actions(parser, command)
        assert "toy" in actions["--estimator"].choices
        assert "toy (tests/test_registry.py)" in actions["--estimator"].help
        assert actions["--boost"].help == "toy: how far the toy turns its gate up (default 2)"
        # A shared option it takes through a field of another name: its default joins the others'.
        assert "ml, gpda, max-mixture, multimodal, toy: default 3" in actions["--gate"].help

    args = parser.parse_args(["run", "s.json", "-o", "r.json", "--estimator", "toy", "--boost", "5", "--gate", "2",
                              "--smoother", "lag:4"])
    estimator = estimator_from_args(args)
    assert estimator == Toy(boost=5, candidates=2, smoother=hs.Lag(4))
    assert estimator.describe().endswith("; classifier=scenario, candidates=2, gate_probability=0.999, "
                                         "max_hypotheses=64, gn_max_steps=20, smoother=lag:4, boost=5")
    assert estimator.describe().startswith("hybridslam ") and "a toy (tests/test_registry.py)" in estimator.describe()

    with pytest.raises(cli.CLIError, match="--boost: expected a positive number, got 0"):
        estimator_from_args(parser.parse_args(["run", "s.json", "-o", "r.json", "--estimator", "toy", "--boost", "0"]))
    with pytest.raises(ValueError, match=r"--boost: the ml estimator has no such setting \(it applies to: toy\)"):
        hs.make_estimator("ml", boost=3)
    monkeypatch.delitem(registry.ESTIMATORS, "toy")
    assert "--boost" not in _actions(cli.build_parser(), "run")


# The options each estimator took when they were listed by hand beside the classes, and the
# unknown map's new-landmark rule (thesis Sec. 3.2.1) that every estimator takes.
COMMON = {"classifier", "gn_max_steps", "max_detections", "max_steps", "smoother", "new_landmark"}
TAKEN = {
    "hybrid": COMMON | {"capacity", "prune_ratio",
               "gate", "weights", "samples", "visibility_temperature", "max_children", "exhaustive", "clutter",
               "merge_threshold", "gate_probability"},
    "ml": COMMON | {"gate", "gate_probability",
           "max_children", "clutter"},
    "multimodal": COMMON | {"capacity", "samples",
                   "gate", "max_children", "merge_threshold", "association_prior", "proposal", "clutter"},
}
TAKEN["gpda"] = TAKEN["max-mixture"] = TAKEN["ml"]


@pytest.mark.parametrize("name", list(TAKEN))
def test_each_estimator_takes_the_options_it_always_took(name):
    assert set(options_of(hs.ESTIMATORS[name])) == TAKEN[name]


def test_the_commands_offer_the_flags_they_always_offered():
    offered = {o.flag for o in all_options(hs.ESTIMATORS).values() if o.command_line}
    assert offered == {"--samples", "--capacity", "--prune-ratio", "--weights", "--gate", "--max-children",
                       "--exhaustive", "--clutter", "--smoother", "--max-detections", "--max-steps",
                       "--new-landmark", "--merge-threshold", "--gate-probability"}


@pytest.mark.parametrize("options, field, value", [
    ({"weights": "sampled", "samples": 10}, "weights", hs.Sampled(10)),
    ({"samples": 10}, "weights", hs.LaplaceIS(10)),
    ({"exhaustive": True}, "branching", hs.estimators.hybrid.branching.Exhaustive()),
    ({"max_children": 5}, "branching", hs.estimators.hybrid.branching.Beam(5)),
    ({"smoother": "filter"}, "smoother", hs.Filter()),
    ({"gate": 2}, "gate", 2),
])
def test_options_that_build_a_field(options, field, value):
    assert getattr(hs.make_estimator("hybrid", **options), field) == value


def test_options_that_contradict_each_other_are_refused():
    with pytest.raises(ValueError, match="--max-children: the exhaustive enumeration keeps every child"):
        hs.make_estimator("hybrid", exhaustive=True, max_children=4)
    with pytest.raises(ValueError, match="--samples: the linearized weights draw no samples"):
        hs.make_estimator("hybrid", weights="linearized", samples=4)


def test_two_estimators_cannot_define_one_option_differently():
    class Other(Toy):
        boost: int = eqx.field(default=2, static=True, metadata=setting(Option("boost", "something else")))

    with pytest.raises(TypeError, match="--boost: defined differently by toy and other"):
        all_options({"toy": Toy, "other": Other})


def test_the_help_groups_estimators_by_what_an_option_means_for_them():
    estimators = {"hybrid": hs.Hybrid, "ml": hs.ML, "multimodal": hs.Multimodal}
    gate = all_options(estimators)["gate"]
    assert option_help(gate, estimators) == ("candidate objects per detection after Mahalanobis gating "
                                             "(hybrid: default every object; ml, multimodal: default 3)")
    assert option_help(gate, estimators, default="5").endswith("(default 5)")
    smoother = all_options(estimators)["smoother"]
    assert option_help(smoother, estimators).endswith("(default full)")  # the same for every estimator: no names


@pytest.mark.parametrize("name", list(TAKEN))
def test_a_scenario_with_more_detections_than_slots_is_refused_by_name(name):
    scenario = hs.simulate(seed=0, steps=3)  # a step with 2 detections
    with pytest.raises(ValueError, match="max_detections: 1 slots, but a step of the scenario has 2 detections"):
        hs.make_estimator(name, max_detections=1).init(scenario)
