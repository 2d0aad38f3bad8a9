"""Tactile video to estimate: the synthetic 2-D box-press scene, ``tacest record --source
video`` making a 2-D run from a 2-D finger log, and ``tacest estimate`` accepting it."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.estimation.data import touching
from tacest.estimation.estimator import ImplicitEstimator
from tacest.io.run import read_run
from tacest.sensors.synth_tactile import SynthConfig, generate, write_sequence

TACEST = str(Path(sys.executable).with_name("tacest"))
#: 320x240 test frames analysed at full resolution (see tests/test_video_flow.py)
SMALL_FLAGS = ["--flow-scale", "1.0"]
#: IPOPT capped at a few iterations: the test is that the run is accepted and the problem
#: built and solved, not how far a solve gets (a full solve of this scene takes ~20 s)
TINY_SOLVER = "[solver]\nmax_iter = 3\nstage_max_iter = 3\n"
#: the finger log is a PCHIP path sampled at 200 Hz, read back by linear interpolation at
#: the frame times: between two log samples 5 ms apart the path bends by at most ~0.05 mm
#: near a contact's start or end (5 mm stand-off covered in one 33 ms frame); 0.1 mm bounds it
TOL_PATH = 1e-4  # m


def _tacest(*args):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def press(tmp_path_factory):
    cfg = SynthConfig(width=320, height=240, n_frames=90, seed=2, dim=2, scene="box-press")
    seq = generate(cfg)
    out = tmp_path_factory.mktemp("press")
    return seq, write_sequence(seq, out)


def test_box_press_finger_log_is_consistent_with_the_scene(press):
    seq, paths = press
    cfg = seq.config
    w, h = cfg.box_size_m
    r = seq.calib.finger_radius
    # the finger log at the frame times, as the recorder reads it
    x = np.interp(seq.times, seq.finger_time, seq.finger_position[:, 0])
    y = np.interp(seq.times, seq.finger_time, seq.finger_position[:, 1])
    gap = (-0.5 * w) - x - r  # m, fingertip sphere to the left face (negative: overlap)
    on = seq.contact.astype(bool)
    assert 10 <= on.sum() < len(on) - 20
    np.testing.assert_allclose(gap[on], -cfg.press_depth_m * seq.depth[on], atol=TOL_PATH)
    assert np.all(gap[~on] >= cfg.standoff_m - TOL_PATH)
    # between frames too: the sphere never overlaps the face outside a contact
    frame_of = np.clip(np.round((seq.finger_time - seq.times[0]) * cfg.fps).astype(int), 0, len(on) - 1)
    far = ~on[frame_of] & ~on[np.clip(frame_of - 1, 0, None)] & ~on[np.clip(frame_of + 1, None, len(on) - 1)]
    assert np.all((-0.5 * w) - seq.finger_position[far, 0] - r > 0)
    # pressed on the face, not at a corner; the truth normal is the face's (-1, 0)
    assert np.all((y[on] >= 0.25 * h) & (y[on] <= 0.75 * h))
    np.testing.assert_allclose(seq.normal[on], np.tile([-1.0, 0.0], (on.sum(), 1)), atol=1e-12)
    scene = json.loads(paths["scene"].read_text())
    np.testing.assert_allclose(scene["box_vertices_m"], seq.box_vertices)
    assert paths["finger_log"].read_text().startswith("t,x,y\n")


def test_box_press_needs_2d():
    with pytest.raises(ValueError, match="2-D"):
        generate(SynthConfig(width=160, height=120, n_frames=20, dim=3, scene="box-press"))


def test_video_run_from_a_2d_log_is_2d_and_estimate_accepts_it(press, tmp_path):
    seq, paths = press
    run_path = tmp_path / "run.h5"
    p = _tacest("record", "--source", "video", "--frames", paths["frames"], "--calib", paths["calib"],
                "--finger-log", paths["finger_log"], "-o", run_path, *SMALL_FLAGS)
    assert p.returncode == 0, p.stderr
    assert "2-D run: contact normals projected onto the x-y plane" in p.stderr
    run = read_run(run_path)
    assert run.dim == 2 and run.finger_position.shape == (90, 1, 2) and run.force is None
    c = run.contact[:, 0].astype(bool)
    truth = seq.contact.astype(bool)
    # the detector may miss a shallow ramp frame at either end of a contact (docs/tactile_video.md)
    assert np.count_nonzero(c != truth) <= 4 and np.all(truth[c])
    # in-plane normals: the face's (-1, 0) within the 5 degrees
    ang = np.degrees(np.arccos(np.clip(-run.normal[c, 0, 0], -1, 1)))
    assert np.max(ang) < 5.0
    settings = json.loads(run.extra_attrs["video_settings"])
    assert 0.0 <= settings["normal_out_of_plane_deg"]["max"] < 5.0

    # the estimator takes the run and builds its problem
    est = ImplicitEstimator([run], "box")
    assert est.structures[0].T == 90 and est.structures[0].F == 1
    np.testing.assert_array_equal(touching(run)[:, 0], c)

    # tacest estimate, 2-D, box: an estimate (exit 0) or an honest solver failure in one line
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_SOLVER)
    out = tmp_path / "est.h5"
    e = _tacest("estimate", run_path, "--shape", "box", "--config", cfg, "--quiet", "-o", out)
    if e.returncode == 0:
        assert out.exists()
    else:
        lines = e.stderr.strip().splitlines()
        assert e.returncode == 2 and len(lines) == 1, e.stderr
        assert lines[0].startswith("tacest: error: IPOPT failed"), lines[0]
        assert not out.exists()


def test_synth_command_box_press(tmp_path):
    cmd = [sys.executable, "-m", "tacest.sensors.synth_tactile"]
    p = subprocess.run(cmd + [tmp_path / "s", "--frames", "12", "--size", "160x120", "--scene", "box-press"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in (tmp_path / "s").iterdir()) == ["calib.json", "fingers.csv", "frames",
                                                                  "scene.json", "truth.csv"]
    assert (tmp_path / "s" / "fingers.csv").read_text().startswith("t,x,y\n")
    p = subprocess.run(cmd + [tmp_path / "t", "--frames", "12", "--size", "160x120", "--scene", "box-press",
                              "--dim", "3"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "box-press is 2-D" in p.stderr
