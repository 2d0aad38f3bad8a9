"""Which of the sampler's seeded runs become NLP starts (smc.best_lineages), in 2-D
and 3-D: the highest likelihoods, distinct boxes, in the runs' order."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.config import load_config
from tacest.estimation.smc import SAME_BOX, best_lineages


def _result(seed, ll, extents):
    return SimpleNamespace(seed=seed, log_likelihood=ll, extents=np.asarray(extents, float))


def test_the_best_likelihoods_are_kept_in_the_runs_order():
    runs = [_result(0, -2118.0, [0.10, 0.12, 0.07]), _result(1, -16.0, [0.11, 0.12, 0.07]),
            _result(2, -3892.0, [0.09, 0.10, 0.08]), _result(3, -900.0, [0.20, 0.05, 0.07])]
    assert [r.seed for r in best_lineages(runs, 1)] == [1]
    assert [r.seed for r in best_lineages(runs, 2)] == [1, 3]  # seed order, not likelihood order
    assert [r.seed for r in best_lineages(runs, 4)] == [0, 1, 2, 3]


def test_a_run_whose_box_repeats_a_better_one_is_left_out():
    """Within SAME_BOX (2 %) in every extent: the same start twice, so the next best
    distinct one is taken instead; just outside it, both are kept."""
    a = _result(0, -10.0, [0.10, 0.10])
    same = _result(1, -20.0, [0.10 * (1 + 0.5 * SAME_BOX), 0.10])
    other = _result(2, -30.0, [0.10 * (1 + 2 * SAME_BOX), 0.10])
    assert [r.seed for r in best_lineages([a, same, other], 2)] == [0, 2]
    assert [r.seed for r in best_lineages([a, same, other], 3)] == [0, 2]  # fewer where they repeat


def test_equal_likelihoods_keep_the_lower_seed():
    runs = [_result(0, -5.0, [0.1, 0.1]), _result(1, -5.0, [0.2, 0.2])]
    assert [r.seed for r in best_lineages(runs, 1)] == [0]


@pytest.mark.parametrize("section", ["solver", "solver3d"])
def test_more_starts_than_runs_is_refused(section):
    with pytest.raises(TacestError, match=f"{section}.sampler_starts"):
        load_config(overrides={section: {"sampler_runs": 2, "sampler_starts": 3}})
    with pytest.raises(TacestError, match=f"{section}.sampler_starts"):
        load_config(overrides={section: {"sampler_starts": 0}})


def test_3d_starts_are_the_configured_lineages(monkeypatch):
    """Estimator3D.sampled_starts offers solver3d.sampler_starts lineages of
    solver3d.sampler_runs runs, each labelled with its seed and likelihood."""
    from tacest.estimation import estimator3d

    lls = {0: -300.0, 1: -20.0, 2: -4000.0, 3: -50.0}
    made = []

    def fake_smc(runs, L, m0, extents0, settings):
        made.append(settings.seed)
        return SimpleNamespace(seed=settings.seed, log_likelihood=lls[settings.seed],
                               extents=np.full(3, 0.1 + 0.01 * settings.seed), poses=[np.zeros((5, 7))],
                               max_tilt_deg=10.0 * settings.seed)

    monkeypatch.setattr(estimator3d, "smc_start_3d", fake_smc)
    monkeypatch.setattr(estimator3d, "touch_inconsistency_3d", lambda run, E, P: np.zeros(1))
    cfg = load_config(overrides={"solver3d": {"sampler_runs": 4, "sampler_starts": 2}, "solver": {"start_workers": 1}})
    sc = SimpleNamespace(L=0.1, m0=0.5)
    tracked = SimpleNamespace(extents=np.ones(3))
    starts = estimator3d.sampled_starts_3d([SimpleNamespace()], sc, tracked, cfg)
    assert sorted(made) == [0, 1, 2, 3]
    assert [s.extra["sampler_seed"] for s in starts] == [1, 3]
    assert [s.extra["log_likelihood"] for s in starts] == [-20.0, -50.0]
    assert all(s.label == "sampler" for s in starts)
