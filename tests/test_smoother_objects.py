"""Strategies as objects: the smoother settings (Filter / Full / Lag) answer what the estimators ask
of them, and the factor-graph solver's elimination orders and termination config are objects that
give what their names give."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridslam as hs
from hybridslam.estimators.smoothers import SMOOTHERS, parse_smoother
from hybridslam.estimators.smoothers import AbstractSmoother, Closing, Filter, Full, Incremental, Lag
from hybridslam.estimators.smoothers.factors import data_log
from hybridslam.inference import smoother as sm
from tests.test_smoother import N, P, _graph


@pytest.mark.parametrize("text", ["filter", "full", "lag:1", "lag:50", "incremental:1", "incremental:50"])
def test_a_smoother_prints_as_its_option_and_parses_back(text):
    smoother = parse_smoother(text)
    assert isinstance(smoother, AbstractSmoother)
    assert str(smoother) == smoother.name == text
    assert parse_smoother(str(smoother)) == smoother


def test_a_smoother_is_offered_by_its_line_in_the_registry(monkeypatch):
    """Adding a smoother is one class and one line in ``SMOOTHERS``: the parser reads its spelling and
    ``--smoother``'s metavar and help are written from the registry."""
    from hybridslam.estimators import options, smoothers

    class Every(Lag):  # a toy: spelled "every:L", a class of one argument like Lag
        spelling = "every:L"
        summary = "a toy"

        @property
        def name(self) -> str:
            return f"every:{self.length}"

    assert parse_smoother("lag:4") == Lag(4)
    with pytest.raises(ValueError, match="expected full, lag:L, incremental:L or filter"):
        parse_smoother("every:4")
    monkeypatch.setattr(smoothers, "SMOOTHERS", (*SMOOTHERS, Every))
    assert parse_smoother("every:4") == Every(4) and str(parse_smoother("every:4")) == "every:4"
    for bad in ("every:0", "every:", "every"):
        with pytest.raises(ValueError, match="or every:L"):
            parse_smoother(bad)
    assert options.SMOOTHER.metavar == "{" + ",".join(s.spelling for s in SMOOTHERS) + "}"
    assert all(f"{s.spelling}: {s.summary}" in options.SMOOTHER.help for s in SMOOTHERS)


def test_what_the_estimators_ask_a_smoother(unchecked_types):
    assert (Filter().smooths, Full().smooths, Lag(3).smooths) == (False, True, True)
    assert (Filter().whole_trajectory, Full().whole_trajectory, Lag(3).whole_trajectory) == (False, True, False)
    # incremental:L steps as lag:L and closes the run with the whole graph; the others close as they step.
    assert not Incremental(3).whole_trajectory and Incremental(3).closing() == Closing(max_steps=100)
    assert Closing().whole_trajectory and all(s.closing() is s for s in (Filter(), Full(), Lag(3)))
    ml = hs.make_estimator("ml", smoother=Incremental(3))
    assert ml.closing().smoother == Closing(max_steps=100) and ml.stepping().closing() is not ml.stepping()
    assert hs.make_estimator("ml", smoother=Lag(3)).closing().smoother == Lag(3)
    scenario = hs.simulate(0, steps=3)
    log = data_log(scenario, 3, max(scenario.max_detections, 1), scenario.num_objects)
    assert Filter().init_window(log) is None and Full().init_window(log, 5) is None
    window = Lag(3).init_window(log, 5)
    assert window is not None and window.mean.shape == (5, log.prior_mean.shape[0])
    np.testing.assert_array_equal(np.asarray(window.info[2]), np.asarray(log.prior_info))
    with pytest.raises(ValueError, match="filter"):
        Filter().smooth(*([None] * 10))  # type: ignore[arg-type]


@pytest.mark.parametrize("make", [lambda s: hs.Hybrid(smoother=s), lambda s: hs.Multimodal(smoother=s),
                                  lambda s: hs.make_estimator("ml", smoother=s)])
def test_a_smoother_that_is_no_smoother_is_refused_by_name(make, unchecked_types):
    with pytest.raises(ValueError, match=r"\.smoother: expected a smoother \(an AbstractSmoother: Full\(\), Lag\(L\), Incremental\(L\), Filter\(\)\)"):
        make(object())


def test_elimination_objects_give_what_their_names_give(unchecked_types):
    graph = _graph(np.random.default_rng(3))
    pairs = [("poses-first", sm.PosesFirst()), ("objects-first", sm.ObjectsFirst()), ("dense", sm.Dense()),
             ("auto", sm.Auto())]
    for name, strategy in pairs:
        assert sm.as_elimination(name) == strategy

    @jax.jit  # one program for the eight solves (op by op, each of their few hundred operations compiles alone)
    def solves(graph):
        lin = sm.linearize(graph, jnp.zeros((P, 3)), jnp.zeros((N, 3))).damped(jnp.asarray(1e-3))
        return [(sm.solve_normal(lin, name), sm.solve_normal(lin, strategy)) for name, strategy in pairs]

    for (name, _), (by_name, by_object) in zip(pairs, solves(graph), strict=True):
        for a, b in zip(by_name, by_object):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13, err_msg=name)
    assert sm.resolve_method(sm.Auto(), 61, 70) == "objects-first"
    assert sm.Auto().resolve(201, 15, True) == sm.PosesFirst()
    with pytest.raises(ValueError, match="method"):
        sm.as_elimination("cholmod")  # type: ignore[arg-type]


def test_the_termination_config_is_what_the_keywords_were():
    graph = _graph(np.random.default_rng(4))
    start = (jnp.zeros((P, 3)), jnp.zeros((N, 3)))
    config = sm.TerminationConfig(cost_rtol=1e-10, lambda_init=1e-3)

    @jax.jit  # one program for both solves
    def both(graph, poses, objects):
        return (sm.solve(graph, poses, objects, max_steps=30, cost_rtol=1e-10, lambda_init=1e-3),
                sm.levenberg_marquardt(graph, poses, objects, config, max_steps=30, method=sm.Auto()))

    by_keywords, by_config = both(graph, *start)
    np.testing.assert_allclose(np.asarray(by_config.poses), np.asarray(by_keywords.poses), rtol=0, atol=1e-12)
    assert int(by_config.steps) == int(by_keywords.steps)


@pytest.mark.parametrize("text, smoother", [("full", Full()), ("filter", Filter()), ("lag:7", Lag(7)),
                                            ("incremental:7", Incremental(7))])
def test_the_command_line_parses_the_smoother_once_into_the_object(text, smoother):
    """``--smoother`` is parsed at the boundary: the namespace holds the smoother object, which
    ``make_estimator`` takes as it is; a bad text is argparse's one-line error."""
    from hybridslam import cli

    args = cli.build_parser().parse_args(["run", "s.json", "-o", "r.json", "--smoother", text])
    assert isinstance(args.smoother, AbstractSmoother) and args.smoother == smoother
    assert hs.make_estimator("ml", smoother=args.smoother).smoother == smoother
    for bad in ("lag:0", "incremental:0", "incremental:", "incremental"):
        with pytest.raises(cli.CLIError, match="--smoother: expected full, lag:L, incremental:L or filter"):
            cli.build_parser().parse_args(["run", "s.json", "-o", "r.json", "--smoother", bad])


def test_a_smoother_without_its_option_text_cannot_be_made():
    """``name`` (the ``--smoother`` text) is abstract: a new smoother that forgets it fails at construction."""

    class Nameless(AbstractSmoother):
        pass

    with pytest.raises(TypeError, match="abstract"):
        Nameless()


def test_a_study_refuses_the_incremental_smoother_before_any_work(tmp_path, capsys):
    """A batched study has no per-track last step for ``incremental:L``'s closing solve: a one-line
    error naming the smoother, and nothing written."""
    from hybridslam import cli
    from hybridslam.studies.batch import check_batchable

    assert cli.main(["sweep", "-o", str(tmp_path / "study"), "--smoother", "incremental:5"]) == 2
    err = capsys.readouterr().err
    assert "smoother=incremental:5" in err and "lag:L" in err and "Traceback" not in err
    assert not (tmp_path / "study").exists()
    check_batchable(hs.make_estimator("hybrid", smoother=Lag(5)))  # lag:L, full and filter batch
    with pytest.raises(ValueError, match="batched study"):
        check_batchable(hs.make_estimator("ml", smoother=Incremental(5)))
