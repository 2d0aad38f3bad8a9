"""The shooting baseline (tacest.estimation.shooting): known-answer recovery from its own
noiseless simulation, the 3-D failure path, and a finite-difference check of the loss's
gradient through the simulation."""

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.dims import estimate_runs
from tacest.estimation.shooting import ShootingEstimator, simulate_run
from tacest.io.run import Run, read_run, write_run

#: the synthetic object: a box 8 cm wide and 6 cm high (shape parameters in units of the
#: default length scale L = 0.1 m), 0.4 kg, ground friction 0.5, finger friction 0.3
L = 0.1
S_TRUE = np.array([0.8, 0.6])
MASS, MU_G, MU_F = 0.4, 0.5, 0.3

#: fingertip waypoints (m) and segment durations (s): push the left face 1.3 cm at
#: ~5 cm/s, lift over, press the top face, go round and push the right face back 8 mm.
#: Touches on both sides and on top make width, height and position identifiable (one
#: face alone fixes only where that face is: DESIGN, "Identifiability").
WAYPOINTS = [(-0.053, 0.03), (-0.037, 0.03), (-0.05, 0.03), (-0.05, 0.08), (0.01, 0.08), (0.01, 0.072),
             (0.01, 0.0675), (0.01, 0.085), (0.085, 0.085), (0.085, 0.03), (0.066, 0.03), (0.055, 0.03)]
DURATIONS = [0.3, 0.05, 0.08, 0.08, 0.04, 0.12, 0.05, 0.08, 0.08, 0.03, 0.25]


def finger_template(waypoints=WAYPOINTS, durations=DURATIONS, dt=0.01) -> Run:
    """A run with a fingertip moving linearly between waypoints and empty tactile streams."""
    W = np.asarray(waypoints, float)
    pts = [W[0]]
    for a, b, d in zip(W[:-1], W[1:], durations):
        n = int(round(d / dt))
        pts += list(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    fp = np.array(pts)[:, None, :]
    T = fp.shape[0]
    return Run(dim=2, dt=dt, time=np.arange(T) * dt, gravity=np.array([0.0, -9.81]), source="test",
               finger_position=fp, finger_radius=np.array([0.01]), contact=np.zeros((T, 1), np.uint8),
               normal=np.full((T, 1, 2), np.nan), force=np.zeros((T, 1, 2)), prior={"size_bound": 0.3})


@pytest.fixture(scope="module")
def synthetic_run():
    return simulate_run(finger_template(), "box", S_TRUE, MASS, MU_G, MU_F, start=[0.0, 0.0])


def test_synthetic_run_touches_three_faces(synthetic_run):
    run = synthetic_run
    on = run.contact[:, 0] == 1
    n = np.round(run.normal[on, 0], 1)
    for face in ([-1, 0], [0, 1], [1, 0]):
        assert np.any(np.all(n == face, axis=1)), f"no touch on the face with normal {face}"
    # the object slid: pushed right, then back
    assert np.ptp(run.truth.pose[:, 0]) > 0.01


def test_recovers_shape_and_friction_times_mass(synthetic_run):
    est = estimate_runs([synthetic_run], "box", method="shooting")
    assert est.method == "shooting"
    assert est.success and est.solver_status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    # The model is exact and the data noiseless; the only residuals left at the truth are
    # the model's own fingertip penetrations in the contact-gap term (~0.1 mm against
    # sigma 0.5 mm), which pull the fit by far less than this.  0.5 mm is one contact-gap
    # sigma and 1 % of the box's smaller side.
    SHAPE_TOL = 5e-4  # m
    V = est.vertices
    w, h = np.ptp(V[:, 0]), np.ptp(V[:, 1])
    assert abs(w - S_TRUE[0] * L) < SHAPE_TOL and abs(h - S_TRUE[1] * L) < SHAPE_TOL, (w, h)
    # mu_g · m is what steady sliding measures (force sigma 0.05 N against mu m g = 2 N):
    # 2 % is ten force sigmas of a single sample, far looser than ~100 sliding samples allow
    MU_M_REL_TOL = 0.02
    mu_m = est.params["friction_ground"] * est.params["mass"]
    assert abs(mu_m - MU_G * MASS) / (MU_G * MASS) < MU_M_REL_TOL, mu_m
    # the estimated trajectory follows the true one to within the shape tolerance
    run_est = est.runs[0]
    assert run_est.pose.shape == synthetic_run.truth.pose.shape
    assert np.max(np.abs(run_est.pose[:, :2] - synthetic_run.truth.pose[:, :2])) < SHAPE_TOL
    assert set(run_est.residuals) == {"force", "normal", "contact", "pose"}
    assert all(r.shape == (synthetic_run.n_samples,) for r in run_est.residuals.values())


def test_three_d_run_is_rejected(tmp_path):
    T = 5
    run = Run(dim=3, dt=0.01, time=np.arange(T) * 0.01, gravity=np.array([0.0, 0.0, -9.81]), source="test",
              finger_position=np.zeros((T, 1, 3)) + [0.0, 0.0, 0.2], finger_radius=np.array([0.01]),
              contact=np.zeros((T, 1), np.uint8), normal=np.full((T, 1, 3), np.nan))
    path = tmp_path / "run3d.h5"
    write_run(run, path)
    with pytest.raises(TacestError, match="3-D"):
        estimate_runs([read_run(path)], "box", method="shooting")


def test_loss_gradient_matches_central_differences(synthetic_run):
    """The loss's gradient through 40 samples x 10 substeps of simulation against central
    differences at a random point near the truth (in contact with the left face)."""
    short = synthetic_run.replace(**{k: getattr(synthetic_run, k)[:40] for k in
                                     ("time", "finger_position", "contact", "normal", "force")}, truth=None)
    est = ShootingEstimator([short], "box")
    pr = est.problem
    rng = np.random.default_rng(0)
    z = np.array([*S_TRUE, np.log(MASS / est.scales.m0), 0.0, MU_G, MU_F, 0.0, 0.0])
    # perturb all but the start angle: a box started on a corner falls onto its face, an
    # impact sharper than the smooth contact scale below (the estimator holds a box's start
    # angle anyway); the derivative with respect to the angle is still checked, at 0
    z[:-1] += rng.normal(0.0, 0.02, z.size - 1)
    f, g = pr.loss_grad(z, est.p)
    g = np.asarray(g).reshape(-1)
    # Central differences err by h² f''' / 6 (truncation) + eps |f| / h (rounding).  The
    # loss varies on the contact smoothing scale, 1e-4 m = 1e-3 in the scaled variables,
    # so with h = 1e-6 the truncation is ~(h / 1e-3)² = 1e-6 relative and the rounding
    # ~1e-16 · f / h = 1e-10 f; 1e-4 relative (plus 1e-6 of the largest component) leaves
    # room for the substeps' sharper transitions.
    h = 1e-6
    fd = np.array([(float(pr.loss(z + h * e, est.p)) - float(pr.loss(z - h * e, est.p))) / (2 * h)
                   for e in np.eye(z.size)])
    np.testing.assert_allclose(fd, g, rtol=1e-4, atol=1e-6 * np.max(np.abs(g)))
