"""A start from an earlier estimate of the first samples of the same runs (2-D:
estimator.previous_start_2d; the 3-D one is in test_initial3d.py and test_plan3d.py):
the continued push-tracked trajectory, the failure paths, and a fit of two pokes that
starts first from an estimate of the first one."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.estimator import ImplicitEstimator, estimate_2d
from tacest.estimation.initial import continued_trajectory, push_tracker_batch
from tacest.io.estimate import Estimate, RunEstimate
from tacest.io.run import read_run
from tests.reliability_files import make_run


@pytest.fixture(scope="module")
def two_pokes(tmp_path_factory):
    """(run of 2 simulated gentle pokes with truth, the sample where the second begins)."""
    run = read_run(make_run(tmp_path_factory.mktemp("previous") / "run.h5", seed=3, pokes=2))
    return run, int(run.actions.segments[1][0])


def _truth_estimate(run, T0, shape="box", dim=2, n_runs=1) -> Estimate:
    """An estimate holding the truth of the first T0 samples of ``run``."""
    tr = run.truth
    return Estimate(dim=dim, shape=shape, vertices=np.asarray(tr.vertices, float),
                    params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                            "friction_finger": tr.friction_finger},
                    runs=[RunEstimate(pose=np.asarray(tr.pose, float)[:T0],
                                      velocity=np.zeros((T0, 3)))] * n_runs)


def test_a_continued_trajectory_keeps_the_earlier_poses_and_is_the_tracker_from_there(two_pokes):
    run, T0 = two_pokes
    V = np.asarray(run.truth.vertices, float)
    pose0 = np.asarray(run.truth.pose, float)[0]
    full = push_tracker_batch(run, V[None], pose0[None])[0]
    # continued from the tracker's own pose, it is the tracker's track (the same steps)
    np.testing.assert_allclose(continued_trajectory(run, V, full[:T0]), full, atol=1e-12)
    before = np.asarray(run.truth.pose, float)[:T0]
    track = continued_trajectory(run, V, before)
    np.testing.assert_array_equal(track[:T0], before)
    # the tracker never rotates: the orientation holds at the earlier estimate's last one
    np.testing.assert_allclose(track[T0:, 2], before[-1, 2], atol=1e-12)
    with pytest.raises(ValueError, match="poses_before"):
        continued_trajectory(run, V, np.zeros((run.n_samples + 1, 3)))


@pytest.mark.parametrize("bad, message", [
    (dict(shape="polygon:6"), "not a 2-D box"),
    (dict(dim=3), "3-D"),
    (dict(n_runs=2), "has 2 runs"),
])
def test_an_earlier_estimate_that_does_not_fit_is_one_clear_error(two_pokes, bad, message):
    run, T0 = two_pokes
    with pytest.raises(TacestError, match=message):
        ImplicitEstimator([run], "box", previous=_truth_estimate(run, T0, **bad))
    longer = _truth_estimate(run, run.n_samples)
    longer.runs[0].pose = np.concatenate([longer.runs[0].pose, longer.runs[0].pose[-1:]])
    with pytest.raises(TacestError, match=f"does not fit a run of {run.n_samples} samples"):
        ImplicitEstimator([run], "box", previous=longer)


def test_two_pokes_start_first_from_the_estimate_of_the_first(two_pokes):
    """Known answer: the truth of the first poke as the earlier estimate.  Its start is
    solved first and compared.  On this recording (seed 3) the estimator's own starts
    end 4.3 mm off at objective 9.44; from the earlier estimate the kept fit is 0.42 mm
    off at 8.79.  Asserted: within 2 mm of the true box (the gentle 2-D box benchmark's
    median is 0.5 mm; 2 mm fails the 4.3 mm basin) and below the own starts' objective
    (here the fits' search is the same but for the one more start)."""
    import json

    from tacest.geometry.chamfer import chamfer_body

    run, T0 = two_pokes
    est = estimate_2d([run], "box", previous=_truth_estimate(run, T0))
    starts = [a["start"] if "start" in a else "push-tracked" for a in json.loads(est.extra_attrs["starts"])]
    assert starts[0] == "previous estimate"
    assert chamfer_body(est.vertices, np.asarray(run.truth.vertices, float)) < 2e-3
    plain = estimate_2d([run], "box")
    assert est.objective <= plain.objective + 1e-6 * abs(plain.objective)
