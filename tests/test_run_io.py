"""Run file round trip (2-D, 3-D, the real cube tosses) and validation errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from tacest.errors import FileFormatError, TacestError
from tacest.io.run import Actions, Run, Truth, read_run, write_run

CUBE_DIR = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "contactnets-cube"


def make_run(dim=2, T=50, F=1, force=True, truth=True, obs=False) -> Run:
    """A small valid run with deterministic content."""
    rng = np.random.default_rng(0)
    dt = 0.01
    time = np.arange(T) * dt
    fp = rng.normal(size=(T, F, dim)) * 0.05
    contact = np.zeros((T, F), np.uint8)
    contact[10:20] = 1
    normal = np.full((T, F, dim), np.nan)
    n = np.zeros(dim)
    n[0] = -1.0
    normal[contact.astype(bool)] = n
    frc = np.zeros((T, F, dim))
    frc[contact.astype(bool)] = -n * 0.5
    P = 3 if dim == 2 else 7
    pose = np.zeros((T, P))
    if dim == 3:
        pose[:, 3] = 1.0
    run = Run(dim=dim, dt=dt, time=time, gravity=np.r_[np.zeros(dim - 1), -9.81], source="test",
              finger_position=fp, finger_radius=np.full(F, 0.01), contact=contact, normal=normal,
              force=frc if force else None,
              actions=Actions(segments=np.array([[0, 25], [25, T]]), params=np.ones((2, 3)), kind="poke",
                              names=["a", "b", "c"]),
              prior={"size_bound": 0.3, "shape": "box"})
    if obs:
        run.pose_obs = pose.copy()
        run.pose_obs[5] = np.nan
    if truth:
        verts = np.array([[-0.05, -0.03], [0.05, -0.03], [0.05, 0.03], [-0.05, 0.03]]) if dim == 2 \
            else np.array([[sx, sy, sz] for sx in (-.05, .05) for sy in (-.05, .05) for sz in (-.05, .05)])
        run.truth = Truth(pose=pose, vertices=verts, mass=0.3,
                          inertia=1e-3 if dim == 2 else np.eye(3) * 1e-3, friction_ground=0.4,
                          friction_finger=0.3, effects=[{"name": "none"}])
    return run


@pytest.mark.parametrize("dim", [2, 3])
def test_round_trip(tmp_path, dim):
    run = make_run(dim=dim, obs=True)
    path = tmp_path / "r.h5"
    write_run(run, path)
    back = read_run(path)
    assert back.dim == dim and back.dt == run.dt
    for name in ("time", "finger_position", "finger_radius", "force", "pose_obs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(run, name))
    np.testing.assert_array_equal(back.contact, run.contact)
    np.testing.assert_array_equal(np.isnan(back.normal), np.isnan(run.normal))
    np.testing.assert_array_equal(back.actions.segments, run.actions.segments)
    assert back.actions.names == ["a", "b", "c"]
    assert back.truth.mass == 0.3 and back.truth.effects == [{"name": "none"}]
    np.testing.assert_array_equal(back.truth.vertices, run.truth.vertices)
    assert back.prior["size_bound"] == 0.3 and back.prior["shape"] == "box"


def test_no_truth_and_no_force(tmp_path):
    run = make_run(force=False)
    write_run(run, tmp_path / "r.h5", include_truth=False)
    back = read_run(tmp_path / "r.h5")
    assert back.truth is None and back.force is None and back.has_tactile


@pytest.mark.skipif(not CUBE_DIR.is_dir(), reason="shared cube dataset not present")
def test_real_cube_files_read_and_round_trip(tmp_path):
    for name in ("toss_000.h5", "toss_123.h5", "toss_399.h5"):
        run = read_run(CUBE_DIR / name)
        assert run.dim == 3 and run.pose_obs is not None and not run.has_tactile
        assert run.dt == pytest.approx(0.0068)
        write_run(run, tmp_path / name)
        back = read_run(tmp_path / name)
        np.testing.assert_array_equal(back.pose_obs, run.pose_obs)
        assert back.sigma_position == run.sigma_position


# --- validation: every bad file names the file and the offending path ------------------


def _write_then(tmp_path, mutate, **kw):
    path = tmp_path / "bad.h5"
    write_run(make_run(**kw), path)
    with h5py.File(path, "a") as f:
        mutate(f)
    return path


BAD_CASES = {
    "missing time": (lambda f: f.__delitem__("time"), "/time"),
    "wrong version": (lambda f: f.attrs.__setitem__("version", 7), "version"),
    "wrong format": (lambda f: f.attrs.__setitem__("format", "other"), "format"),
    "non-increasing time": (lambda f: f["time"].__setitem__(5, 0.0), "/time"),
    "nan finger": (lambda f: f["robot/finger_position"].__setitem__((3, 0, 0), np.nan), "/robot/finger_position"),
    "non-unit normal": (lambda f: f["tactile/normal"].__setitem__((12, 0), [2.0, 0.0]), "/tactile/normal"),
    "nan normal in contact": (lambda f: f["tactile/normal"].__setitem__((12, 0), [np.nan, np.nan]), "/tactile/normal"),
    "contact not 0/1": (lambda f: f["tactile/contact"].__setitem__((1, 0), 3), "/tactile/contact"),
    "force wrong shape": (lambda f: (f["tactile"].__delitem__("force"),
                                     f["tactile"].create_dataset("force", data=np.zeros((3, 2)))), "/tactile/force"),
    "missing robot": (lambda f: f.__delitem__("robot"), "/robot"),
    "no streams": (lambda f: (f.__delitem__("tactile"), f.__delitem__("robot")), "/tactile"),
    "dim 4": (lambda f: f.attrs.__setitem__("dim", 4), "dim"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_validation_errors_name_file_and_path(tmp_path, case):
    mutate, where = BAD_CASES[case]
    path = _write_then(tmp_path, mutate)
    with pytest.raises(FileFormatError) as err:
        read_run(path)
    msg = str(err.value)
    assert str(path) in msg and where in msg and "\n" not in msg


def test_partial_nan_observation_row_rejected(tmp_path):
    path = _write_then(tmp_path, lambda f: f["observations/pose"].__setitem__((7, 0), np.nan), obs=True)
    with pytest.raises(FileFormatError, match="/observations/pose"):
        read_run(path)


def test_missing_and_non_hdf5_files(tmp_path):
    with pytest.raises(TacestError, match="no such file"):
        read_run(tmp_path / "nope.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    with pytest.raises(TacestError, match="not a readable HDF5"):
        read_run(junk)


def test_write_is_atomic_on_invalid_run(tmp_path):
    """An invalid run is refused before anything is written; no temporary file is left."""
    run = make_run()
    run.normal[12, 0] = [3.0, 0.0]
    with pytest.raises(FileFormatError):
        write_run(run, tmp_path / "x.h5")
    assert list(tmp_path.iterdir()) == []


def test_write_crash_leaves_no_file(tmp_path, monkeypatch):
    import tacest.io.run as runmod

    def boom(f, run, include_truth=True):
        f.create_dataset("time", data=[0.0])
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(runmod, "fill_run_file", boom)
    with pytest.raises(RuntimeError):
        runmod.write_run(make_run(), tmp_path / "x.h5")
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_file_one_line_exit_2(tmp_path):
    path = _write_then(tmp_path, lambda f: f.attrs.__setitem__("version", 9))
    exe = Path(sys.executable).parent / "tacest"
    proc = subprocess.run([str(exe), "estimate", str(path), "-o", str(tmp_path / "e.h5")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert not (tmp_path / "e.h5").exists()
