"""tacest eval: metrics against known answers on hand-built runs and estimates, file
matching, the JSON contract and the error paths of the command.

Runs are built directly as tacest.io.run.Run objects (no simulator): an object slides
along x on the ground while a finger pushes it; estimates are the truth perturbed by
known amounts.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.evaluation.metrics import evaluate, evaluate_files, format_report, match_run, to_jsonable
from tacest.geometry.polygon import box_vertices, polygon_inertia
from tacest.geometry.polytope import box_vertices_3d, polytope_inertia
from tacest.geometry.transforms import quat_from_axis_angle, quat_multiply, quat_to_matrix
from tacest.io.estimate import Estimate, RunEstimate, read_estimate, write_estimate
from tacest.io.h5util import sha256_file
from tacest.io.run import Run, Truth, read_run, write_run

REPO = Path(__file__).resolve().parents[1]
TACEST = REPO / ".venv" / "bin" / "tacest"

W, H, DEPTH = 0.10, 0.06, 0.08  # m, object size
MASS, MU_G, MU_F = 0.5, 0.3, 0.6
T = 240
DT = 0.01
FINGER_R = 0.01

#: Float64 round-off of metrics computed from values ~0.1 m: 1e-12 m is ~1e4 ulps.
ROUNDOFF = 1e-12
#: Quadrature bound of the 2-D Chamfer distance for these shapes: the distance along
#: the boundary is piecewise linear, so the midpoint rule errs only in the cells
#: holding its ~8 kinks, each by at most h²/4 over the perimeter L (h = L/4000):
#: 8 h² / (4 L) = 6e-8 m for L = 0.32 m.
QUAD_2D = 6e-8
#: 3-D: the adaptive 2000-cell surface rule errs by <= 1.8 µm on moved boxes
#: (tacest/geometry/chamfer.py docstring); 5 µm leaves margin and is still 1/20 of
#: the 0.1 mm the metric must resolve.
QUAD_3D = 5e-6


# ---------------------------------------------------------------------------------
# builders


def make_run(dim=2, with_truth=True, T=T, spin=False):
    """A box sliding 5 cm along +x, pushed by one finger from the -x side.
    ``spin``: the box also turns (2-D: about z; 3-D: about the vertical axis)."""
    t = np.arange(T) * DT
    s = 0.05 * np.clip((t - 0.3) / (t[-1] - 0.6), 0.0, 1.0)  # slides from 0.3 s on
    if dim == 2:
        verts = box_vertices(W, H)
        pose = np.zeros((T, 3))
        pose[:, 0] = s
        pose[:, 1] = H / 2
        pose[:, 2] = 0.4 * s / 0.05 if spin else 0.0
        up = np.array([0.0, 1.0])
        fpos = np.stack([s - W / 2 - FINGER_R, np.full(T, H / 2)], 1)[:, None, :]
        inertia = polygon_inertia(verts, MASS)
    else:
        verts = box_vertices_3d([W, DEPTH, H])
        pose = np.zeros((T, 7))
        pose[:, 0] = s
        pose[:, 2] = H / 2
        ang = 0.4 * s / 0.05 if spin else np.zeros(T)
        pose[:, 3:7] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), ang)
        up = np.array([0.0, 0.0, 1.0])
        fpos = np.stack([s - W / 2 - FINGER_R, np.zeros(T), np.full(T, H / 2)], 1)[:, None, :]
        inertia = polytope_inertia(verts, MASS)
    contact = (t >= 0.3).astype(np.uint8)[:, None]
    normal = np.full((T, 1, dim), np.nan)
    e = np.zeros(dim)
    e[0] = -1.0
    normal[contact[:, 0] == 1, 0] = e
    force = np.zeros((T, 1, dim))
    force[contact[:, 0] == 1, 0, 0] = MU_G * MASS * 9.81
    truth = Truth(pose=pose, vertices=verts, mass=MASS, inertia=inertia, friction_ground=MU_G,
                  friction_finger=MU_F, effects=[{"name": "none"}]) if with_truth else None
    g = -9.81 * up
    return Run(dim=dim, dt=DT, time=t, gravity=g, source="test", finger_position=fpos,
               finger_radius=np.array([FINGER_R]), contact=contact, force=force, normal=normal,
               truth=truth)


def make_estimate(run, vertices=None, dpos=None, dangle=0.0, params=None, source_sha256="",
                  source_file="", extra_runs=()):
    """The truth of ``run`` with known perturbations: positions + dpos, orientation
    turned by dangle (about z), shape ``vertices``, parameters ``params``."""
    D = run.dim
    tr = run.truth
    pose = np.array(tr.pose, float)
    if dpos is not None:
        pose[:, :D] += dpos
    if dangle:
        if D == 2:
            pose[:, 2] += dangle
        else:
            dq = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), dangle)
            pose[:, 3:7] = quat_multiply(dq, pose[:, 3:7])
    p = {"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
         "friction_finger": tr.friction_finger}
    p.update(params or {})
    V = 3 if D == 2 else 6
    runs = list(extra_runs) + [RunEstimate(pose=pose, velocity=np.zeros((pose.shape[0], V)),
                                           source_file=source_file, source_sha256=source_sha256)]
    return Estimate(dim=D, shape="box", vertices=tr.vertices if vertices is None else vertices,
                    params=p, runs=runs, solver_status="Solve_Succeeded", success=True)


@pytest.fixture(scope="module")
def files2d(tmp_path_factory):
    """run.h5 with truth, est.h5 (positions +2 mm in x, mass +10 % and flagged not
    identifiable, friction_finger NaN), notruth.h5."""
    d = tmp_path_factory.mktemp("eval2d")
    run = make_run(2)
    write_run(run, d / "run.h5")
    write_run(make_run(2, with_truth=False), d / "notruth.h5")
    est = make_estimate(run, dpos=np.array([0.002, 0.0]),
                        params={"mass": 1.1 * MASS, "friction_finger": float("nan")},
                        source_sha256=sha256_file(d / "run.h5"), source_file=str(d / "run.h5"))
    est.identifiable = {"mass": False}
    write_estimate(est, d / "est.h5")
    return d


def tacest(*args):
    return subprocess.run([str(TACEST), *map(str, args)], capture_output=True, text=True, timeout=120)


# ---------------------------------------------------------------------------------
# metrics, in process


def test_known_answers_2d():
    run = make_run(2)
    d = 0.002  # m, shift along x; the box does not turn
    est = make_estimate(run, dpos=np.array([d, 0.0]), dangle=0.0,
                        params={"mass": 0.55, "friction_ground": 0.27, "inertia": 2 * run.truth.inertia})
    r = evaluate(est, run)
    # a w x h rectangle against itself shifted by d along its w side: h d / (w + h)
    # (derived in tests/test_chamfer.py); the same at every frame
    assert r["chamfer"] == pytest.approx(H * d / (W + H), abs=QUAD_2D)
    assert r["chamfer_max"] == pytest.approx(H * d / (W + H), abs=QUAD_2D)
    assert r["chamfer_body"] < 1e-9  # same shape: alignment to ICP tolerance, 1e-9 m
    assert r["pose_position_rmse"] == pytest.approx(d, abs=ROUNDOFF)
    assert r["pose_angle_rmse"] == pytest.approx(0.0, abs=ROUNDOFF)
    assert r["mass_rel"] == pytest.approx(0.1, abs=ROUNDOFF)
    assert r["friction_ground_rel"] == pytest.approx(0.1, abs=ROUNDOFF)
    assert r["friction_finger_rel"] == pytest.approx(0.0, abs=ROUNDOFF)
    assert r["inertia_rel"] == pytest.approx(1.0, abs=ROUNDOFF)
    assert r["n_samples"] == T
    assert r["n_frames"] == 120  # T = 240 > 200 frames: every 2nd sample
    assert r["solver_status"] == "Solve_Succeeded"


def test_frame_subsampling_and_angle_error_2d():
    run = make_run(2, T=450, spin=True)
    est = make_estimate(run, dangle=0.01)
    r, series = evaluate(est, run, return_series=True)
    assert r["n_frames"] == 150  # ceil(450 / 200) = 3 -> samples 0, 3, ..., 447
    np.testing.assert_array_equal(series["frames"], np.arange(0, 450, 3))
    assert r["pose_angle_rmse"] == pytest.approx(0.01, abs=ROUNDOFF)
    assert r["pose_position_rmse"] == pytest.approx(0.0, abs=ROUNDOFF)
    # turning about the COM by a small angle a moves the boundary by ~|p| a: the
    # Chamfer distance is a fraction of (half-diagonal x a) = 0.58 mm
    assert 1e-5 < r["chamfer"] < 0.0583 * 0.01


def test_known_answers_3d():
    run = make_run(3)
    d = 0.001
    R = quat_to_matrix(quat_from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.7))
    # estimate: same box in a body frame turned by R (vertices R v, inertia R I R^T),
    # with poses turned back so the placed shape is the true one, shifted by d along x
    pose_fix = quat_from_axis_angle(np.array([1.0, 2.0, 3.0]), -0.7)
    est = make_estimate(run, vertices=run.truth.vertices @ R.T, dpos=np.array([d, 0.0, 0.0]),
                        params={"inertia": R @ run.truth.inertia @ R.T, "mass": 0.4})
    est.runs[0].pose[:, 3:7] = quat_multiply(est.runs[0].pose[:, 3:7], pose_fix)
    r = evaluate(est, run)
    # the body frames differ by R, and the world orientations match exactly
    assert r["pose_angle_rmse"] == pytest.approx(0.7, abs=1e-9)  # the relabelled frame shows
    assert r["pose_position_rmse"] == pytest.approx(d, abs=ROUNDOFF)
    assert r["inertia_rel"] == pytest.approx(0.0, abs=1e-12)  # principal moments agree
    assert r["mass_rel"] == pytest.approx(0.2, abs=ROUNDOFF)
    assert r["chamfer_body"] < 1e-6  # identical shapes after ICP: 1 µm (ICP on 2000 samples)
    # the placed shapes are the box and the box shifted by d along x at every frame:
    # compare with a fine (60 000-sample) computation of that static pair
    from tacest.geometry.chamfer import chamfer_shapes

    ref = chamfer_shapes(run.truth.vertices, run.truth.vertices + [d, 0, 0], 60000)
    assert r["chamfer"] == pytest.approx(ref, abs=QUAD_3D)


def test_inertia_rel_3d_frobenius():
    from tacest.evaluation.metrics import _inertia_rel

    It = np.diag([1.0, 2.0, 3.0])
    Ie = np.diag([1.0, 2.0, 3.5])
    assert _inertia_rel(Ie, It, 3) == pytest.approx(0.5 / math.sqrt(14.0), abs=ROUNDOFF)
    assert _inertia_rel([1.0, 2.0, 3.5], It, 3) == pytest.approx(0.5 / math.sqrt(14.0), abs=ROUNDOFF)
    assert math.isnan(_inertia_rel(None, It, 3))
    assert math.isnan(_inertia_rel(Ie, np.full((3, 3), np.nan), 3))


def test_evaluate_errors():
    run = make_run(2)
    est = make_estimate(run)
    with pytest.raises(TacestError, match="has no /truth"):
        evaluate(est, make_run(2, with_truth=False))
    with pytest.raises(TacestError, match="samples"):
        evaluate(est, make_run(2, T=T + 10))
    with pytest.raises(TacestError, match="2-D"):
        evaluate(est, make_run(3))
    with pytest.raises(TacestError, match="no run 3"):
        evaluate(est, run, run_index=3)


def test_match_run():
    run = make_run(2)
    run.filename = "/data/run.h5"
    other = RunEstimate(pose=np.zeros((5, 3)), velocity=np.zeros((5, 3)), source_sha256="abc",
                        source_file="/data/other.h5")
    est = make_estimate(run, source_sha256="feed", source_file="/elsewhere/run.h5", extra_runs=[other])
    assert match_run(est, run, truth_sha256="feed") == (1, "sha256")
    assert match_run(est, run, truth_sha256="nope") == (1, "source_file")  # unique base name
    assert match_run(est, run, run_index=0) == (0, "run-index")
    with pytest.raises(TacestError, match="no run 5"):
        match_run(est, run, run_index=5)
    est.runs[1].source_file = ""
    with pytest.raises(TacestError, match="--run-index"):  # run 0 has 5 samples, truth 240
        match_run(est, run, truth_sha256="nope")
    est.runs = est.runs[1:]
    assert match_run(est, run, truth_sha256="nope") == (0, "length")


def test_json_safe_and_table(files2d):
    report, est, run = evaluate_files(files2d / "est.h5", files2d / "run.h5")
    assert report["matched_by"] == "sha256"
    assert report["params"]["mass"]["identifiable"] is False
    assert report["params"]["friction_ground"]["identifiable"] is None  # not stated
    assert math.isnan(report["friction_finger_rel"])
    js = json.loads(json.dumps(to_jsonable(report), allow_nan=False))
    assert js["friction_finger_rel"] is None
    text = format_report(report)
    assert "chamfer_body" in text and "mass" in text and "n/a" in text and "not identifiable" in text


def test_plot_2d_and_3d(tmp_path):
    from tacest.evaluation.plots import plot_evaluation

    for dim in (2, 3):
        run = make_run(dim, T=60, spin=True)
        est = make_estimate(run, dpos=np.full(dim, 0.001), dangle=0.02)
        report, series = evaluate(est, run, return_series=True)
        out = tmp_path / f"eval{dim}.png"
        plot_evaluation(out, report, series, est, run)
        assert out.stat().st_size > 10_000  # a real figure, not an empty canvas
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------
# the command (subprocess on the installed entry point)


def test_cli_json(files2d, tmp_path):
    png = tmp_path / "fig.png"
    p = tacest("eval", files2d / "est.h5", "--truth", files2d / "run.h5", "--json", "--plot", png)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)  # exactly one JSON object, nothing else on stdout
    for key in ("chamfer", "chamfer_body", "pose_position_rmse", "pose_angle_rmse", "mass_rel",
                "friction_ground_rel", "friction_finger_rel", "inertia_rel", "n_samples", "solver_status"):
        assert key in out, key
    assert out["friction_finger_rel"] is None  # NaN estimate -> null
    assert out["mass_rel"] == pytest.approx(0.1, abs=ROUNDOFF)
    assert out["pose_position_rmse"] == pytest.approx(0.002, abs=ROUNDOFF)
    assert out["chamfer"] == pytest.approx(H * 0.002 / (W + H), abs=QUAD_2D)
    assert png.stat().st_size > 10_000


def test_cli_table(files2d):
    p = tacest("eval", files2d / "est.h5", "--truth", files2d / "run.h5")
    assert p.returncode == 0, p.stderr
    assert "chamfer" in p.stdout and "pose_angle_rmse" in p.stdout and "matched by sha256" in p.stdout


@pytest.mark.parametrize("case", ["no-truth", "wrong-type", "missing", "bad-index"])
def test_cli_errors(files2d, case):
    est, run = files2d / "est.h5", files2d / "run.h5"
    args, needle = {
        "no-truth": ((est, "--truth", files2d / "notruth.h5"), "has no /truth"),
        "wrong-type": ((run, "--truth", run), "tacest.estimate"),
        "missing": ((files2d / "nope.h5", "--truth", run), "no such file"),
        "bad-index": ((est, "--truth", run, "--run-index", "4"), "no run 4"),
    }[case]
    p = tacest("eval", *args, "--json")
    assert p.returncode == 2
    assert p.stdout == ""
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], p.stderr
    assert "Traceback" not in p.stderr


def test_written_estimate_round_trip(files2d):
    """What the tests write is what the CLI reads (guards the fixtures themselves)."""
    est = read_estimate(files2d / "est.h5")
    run = read_run(files2d / "run.h5")
    assert est.runs[0].pose.shape == run.truth.pose.shape
    assert est.runs[0].source_sha256 == sha256_file(files2d / "run.h5")
