"""The tactile stream's interval semantics (SPEC: a sample's flag, force and normal
describe the interval (t-1, t]): in the 2-D model a fingertip's contact frame and lever
are those of the interval's middle; in the 2-D and 3-D models a flag 1 at the last
sample of a touch is checked by the smaller of the fingertip's gaps at the interval's two
ends (a fingertip that lets go, or strikes and bounces, inside the interval touched),
within a touch by the end's gap, and a flag 0 by the end's overlap."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.dynamics.laws import INTERVAL_GAP_SMOOTHING, interval_gap, one_sided
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import finger_start_positions
from tacest.estimation.problem2d import Problem2D, RunStructure
from tacest.model.stage2d import G, G_NAMES
from tacest.geometry.shapes import make_shape
from tacest.geometry.transforms import rot2
from tests.test_estimator import pushed_box_run

L, M0, HALF, RADIUS = 0.1, 0.5, 0.05, 0.01  # m, kg, m (box half-width), m (fingertip)
SIG_NORMAL, SIG_GAP = 0.1, 1e-3


def _stage(angle_start, angle_end, n_meas, away_start=0.0, away_end=0.0, flag=1.0, ends=1.0):
    """Stage outputs of one interval of a 0.1 m box resting on its face while it turns
    from angle_start to angle_end (rad) about its centre; the fingertip touches the left
    face at both ends (it rides along), or is ``away_start`` / ``away_end`` m out from it
    along the face's normal; the flag is ``flag`` (``ends`` 1: the touch's last sample)
    and the normal measured is n_meas."""
    pr = Problem2D(make_shape("box", dim=2), [RunStructure(T=2, F=1)], EstimatorConfig())
    stage = pr.stage_funs[0]
    centre = np.array([0.0, HALF])

    def fingertip(a, away=0.0):
        return centre + rot2(a) @ np.array([-HALF - RADIUS - away, 0.0])

    V = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * HALF  # CCW, body frame
    phys = np.concatenate([V[:, 0] / L, V[:, 1] / L, [1.0, 1.0 / 6, 0.5, 0.5]])
    # data layout of Problem2D.n_data (F = 1)
    d = np.concatenate([fingertip(angle_end, away_end), [0, 0], [flag], n_meas, [0, 0], [0.0], [1.0], [RADIUS],
                        fingertip(angle_start, away_start), [ends], [0, 0, 0], [0.0]])
    assert d.size == pr.n_data(1)
    g = np.ones(len(G_NAMES))
    g[[G["dt"], G["L"], G["m0"], G["nx"], G["ny"], G["h"], G["sig_normal"], G["sig_gap"]]] = \
        [0.01, L, M0, 0.0, 1.0, 0.0, SIG_NORMAL, SIG_GAP]
    g[G["Lam"]] = M0 * 9.81 * 0.01
    q_prev = np.array([centre[0] / L, centre[1] / L, angle_start])
    q = np.array([centre[0] / L, centre[1] / L, angle_end])
    out = stage(q_prev, np.zeros(3), q, np.zeros(3), np.zeros(8), np.zeros(2), phys, d, g, np.zeros(0), np.zeros(0))
    return dict(zip(stage.name_out(), (np.asarray(o).ravel() for o in out)))


def test_the_contact_frame_is_the_interval_middles():
    """A box turning 0.2 rad within one interval: the normal of the middle (turned 0.1)
    fits the measured average exactly; the end's normal (turned 0.2) is off by 2 sin(0.05)
    = 0.1 (one sigma_normal), the start's likewise."""
    left = np.array([-1.0, 0.0])
    mid = _stage(0.0, 0.2, rot2(0.1) @ left)
    # exact geometry: only rounding (1e-12 in units of sigma_normal)
    assert np.abs(mid["normal"]).max() < 1e-12
    for a in (0.0, 0.2):
        off = _stage(0.0, 0.2, rot2(a) @ left)
        assert np.linalg.norm(off["normal"]) == pytest.approx(2 * np.sin(0.05) / SIG_NORMAL, rel=1e-9)


def test_the_contact_flag_is_checked_by_the_gap_at_the_interval_end():
    """The fingertip touches the face at the interval's end (and start): the flag's
    residual is 0, although the fingertip's middle position (a chord's midpoint) is
    inside the turning box's middle pose by (1 - cos 0.1)·0.06 m."""
    out = _stage(0.0, 0.2, np.array([-1.0, 0.0]))
    assert abs(out["contact"][0]) < 1e-9  # m / sigma_gap, rounding only


EPS_GAP = INTERVAL_GAP_SMOOTHING * SIG_GAP  # m, the smooth minimum's offset where the ends differ


def _smooth_min(a, b):
    """The smooth minimum of laws.interval_gap, written out (m)."""
    return 0.5 * (a + b) - np.sqrt((0.5 * (a - b)) ** 2 + EPS_GAP ** 2) + EPS_GAP


@pytest.mark.parametrize("away_start, away_end", [(0.0, 5e-3), (5e-3, 0.0)])
def test_a_fingertip_that_touches_at_one_end_of_the_interval_satisfies_its_flag(away_start, away_end):
    """Flag 1 at a touch's last sample, the fingertip on the face at one end and 5 mm off
    at the other (let go, or struck, inside the interval): the residual is the smooth minimum's offset, EPS_GAP /
    sigma_gap = 0.1 less eps² / |a - b| (0.002), where the end's gap alone would cost 5
    sigma.  Exact to rounding (1e-9 relative)."""
    out = _stage(0.0, 0.0, np.array([-1.0, 0.0]), away_start=away_start, away_end=away_end)
    assert out["contact"][0] == pytest.approx(_smooth_min(0.0, 5e-3) / SIG_GAP, rel=1e-9)
    assert 0.09 < out["contact"][0] <= 0.1


def test_inside_a_touch_the_flag_is_checked_at_the_interval_end():
    """Flag 1 at a sample that is not a touch's last (the touch goes on past the
    interval's end): the fingertip 5 mm off at the end costs its 5 sigma, whatever the
    start's gap (exact: the residual is the end's gap)."""
    out = _stage(0.0, 0.0, np.array([-1.0, 0.0]), away_start=0.0, away_end=5e-3, ends=0.0)
    assert out["contact"][0] == pytest.approx(5.0, rel=1e-9)


def test_a_fingertip_away_at_both_ends_still_misses_its_flag():
    """Flag 1 but the fingertip 3 mm and 5 mm off at the two ends: the residual is the
    nearer gap (plus the offset), 3.1 sigma (the exact smooth minimum, 3.095)."""
    out = _stage(0.0, 0.0, np.array([-1.0, 0.0]), away_start=3e-3, away_end=5e-3)
    assert out["contact"][0] == pytest.approx(_smooth_min(3e-3, 5e-3) / SIG_GAP, rel=1e-9)
    assert 3.0 < out["contact"][0] < 3.1


def test_a_flag_0_is_checked_by_the_end_alone():
    """Flag 0: the fingertip 2 mm inside the face at the interval's start costs nothing
    there (the previous sample's flag covers it); 2 mm clear at the end, only the smooth
    one-sided penalty's tail (4e-5 at 2 sigma clear), where 2 mm inside at the end costs
    its one-sided penalty (a residual of -1.0)."""
    out = _stage(0.0, 0.0, np.zeros(2), away_start=-2e-3, away_end=2e-3, flag=0.0)
    assert abs(out["contact"][0]) < 1e-3
    inside = _stage(0.0, 0.0, np.zeros(2), away_start=2e-3, away_end=-2e-3, flag=0.0)
    assert inside["contact"][0] == pytest.approx(float(one_sided(-2e-3, SIG_GAP)), rel=1e-9)
    assert abs(inside["contact"][0]) > 0.5


@pytest.mark.parametrize("a", [-2e-3, 0.0, 1e-4, 7e-3])
def test_interval_gap_is_exact_for_equal_gaps_and_near_the_minimum_otherwise(a):
    """interval_gap(a, a) = a to rounding (no bias along a sustained touch); for gaps
    apart, within eps of the smaller one (above it)."""
    eps = 5e-5
    assert float(interval_gap(a, a, eps)) == pytest.approx(a, abs=1e-15)
    for b in (a - 3e-3, a + 4e-3, a + 1e-5):
        v = float(interval_gap(a, b, eps))
        assert min(a, b) - 1e-15 <= v <= min(a, b) + eps + 1e-15


def test_3d_stage_flag_over_the_interval():
    """The 3-D model: a 0.1 m cube at rest, a fingertip (radius 1 cm) on its -x face at the
    interval's start and 5 mm off at its end, flag 1 at the touch's last sample: the
    residual is the smooth minimum (as in 2-D); the same fingertip 5 mm off at both ends,
    or inside the touch, costs 5 sigma (1e-9 relative: rounding)."""
    from tacest.geometry.shapes3d import make_shape_3d
    from tacest.model.stage3d import D_NAMES, DF_NAMES, DI, G3, G3_NAMES, NP, StageModel3D

    model = StageModel3D(make_shape_3d("box"), 1)
    stage = model._stage_function()
    names = stage.name_out()
    x = np.zeros(NP)
    x[2], x[3] = HALF / L, 1.0  # centre 5 cm up, identity quaternion
    th = np.zeros(model.n_theta)
    th[: model.n_shape] = np.asarray(model.shape.initial(np.ones(3)), float).ravel()
    g = np.ones(len(G3_NAMES))
    g[G3["L"]], g[G3["m0"]], g[G3["sig_gap"]] = L, M0, SIG_GAP

    def contact(away_start, away_end, ends=1.0):
        d = np.zeros(model.n_d)
        d[DI["dt"]], d[DI["Lam"]], d[DI["grav"]], d[DI["nz"]], d[DI["qw"]] = 0.01, M0 * 9.81 * 0.01, 9.81, 1.0, 1.0
        o = len(D_NAMES)
        f = {n: o + k for k, n in enumerate(DF_NAMES)}
        d[f["cx"]: f["cz"] + 1] = [-HALF - RADIUS - away_end, 0.0, HALF]
        d[f["sx"]: f["sz"] + 1] = [-HALF - RADIUS - away_start, 0.0, HALF]
        d[f["contact"]], d[f["w_tact"]], d[f["radius"]], d[f["nmx"]], d[f["ends"]] = 1.0, 1.0, RADIUS, -1.0, ends
        out = stage(x, x, x, np.zeros(model.K), np.zeros(3), th, d, g)
        return float(np.asarray(out[names.index("contact")]).ravel()[0])

    assert contact(0.0, 5e-3) == pytest.approx(_smooth_min(0.0, 5e-3) / SIG_GAP, rel=1e-9)
    assert contact(5e-3, 5e-3) == pytest.approx(5.0, rel=1e-9)
    assert contact(0.0, 5e-3, ends=0.0) == pytest.approx(5.0, rel=1e-9)


def test_touch_ends_are_the_last_flagged_sample_of_each_touch():
    from tacest.estimation.data import touch_ends

    run = pushed_box_run()
    c = np.zeros_like(run.contact)
    c[[3, 4, 5, 9, -1], 0] = 1  # a touch of three samples, one of one, one at the run's end
    ends = touch_ends(run.replace(contact=c))
    assert sorted(np.flatnonzero(ends[:, 0])) == [5, 9, run.n_samples - 1]


def test_3d_data_hold_each_fingertip_at_its_interval_start():
    from tacest.estimation.data import touch_ends
    from tacest.estimation.estimator3d import data_matrix_3d
    from tacest.model.effect import Scales
    from tacest.model.stage3d import D_NAMES, DF_NAMES
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(seed=0, pokes=1, dim=3, fingers=2, force_stream=False))
    D = data_matrix_3d(run, 2, Scales(L=0.1, m0=0.5, g=9.81))
    for f in range(2):
        o = len(D_NAMES) + len(DF_NAMES) * f + DF_NAMES.index("sx")
        np.testing.assert_array_equal(D[o: o + 3, 1:], run.finger_position[:-1, f].T)
        np.testing.assert_array_equal(D[o: o + 3, 0], run.finger_position[0, f])
        np.testing.assert_array_equal(D[o + 3], touch_ends(run)[:, f])


def test_finger_start_positions_are_the_previous_samples():
    run = pushed_box_run()
    start = finger_start_positions(run)
    assert start.shape == run.finger_position.shape
    np.testing.assert_array_equal(start[1:], run.finger_position[:-1])
    np.testing.assert_array_equal(start[0], run.finger_position[0])
