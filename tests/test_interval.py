"""The tactile stream's interval semantics in the 2-D model (SPEC: a sample's flag, force
and normal describe the interval (t-1, t]): a fingertip's contact frame and lever are
those of the interval's middle, its contact flag is checked by the gap at the end."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import finger_start_positions
from tacest.estimation.problem2d import Problem2D, RunStructure
from tacest.model.stage2d import G, G_NAMES
from tacest.geometry.shapes import make_shape
from tacest.geometry.transforms import rot2
from tests.test_estimator import pushed_box_run

L, M0, HALF, RADIUS = 0.1, 0.5, 0.05, 0.01  # m, kg, m (box half-width), m (fingertip)
SIG_NORMAL, SIG_GAP = 0.1, 1e-3


def _stage(angle_start, angle_end, n_meas):
    """Stage outputs of one interval of a 0.1 m box resting on its face while it turns
    from angle_start to angle_end (rad) about its centre; the fingertip touches the left
    face at both ends (it rides along), the flag is 1 and the normal measured is n_meas."""
    pr = Problem2D(make_shape("box", dim=2), [RunStructure(T=2, F=1)], EstimatorConfig())
    stage = pr.stage_funs[0]
    centre = np.array([0.0, HALF])

    def fingertip(a):
        return centre + rot2(a) @ np.array([-HALF - RADIUS, 0.0])

    V = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * HALF  # CCW, body frame
    phys = np.concatenate([V[:, 0] / L, V[:, 1] / L, [1.0, 1.0 / 6, 0.5, 0.5]])
    # data layout of Problem2D.n_data (F = 1)
    d = np.concatenate([fingertip(angle_end), [0, 0], [1.0], n_meas, [0, 0], [0.0], [1.0], [RADIUS],
                        fingertip(angle_start), [0, 0, 0], [0.0]])
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


def test_finger_start_positions_are_the_previous_samples():
    run = pushed_box_run()
    start = finger_start_positions(run)
    assert start.shape == run.finger_position.shape
    np.testing.assert_array_equal(start[1:], run.finger_position[:-1])
    np.testing.assert_array_equal(start[0], run.finger_position[0])
