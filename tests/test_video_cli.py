"""``tacest record --source video`` end to end through the installed command."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.io.run import read_run
from tacest.sensors.synth_tactile import SynthConfig, generate, write_sequence

TACEST = str(Path(sys.executable).with_name("tacest"))
#: 320x240 test frames analysed at full resolution (see tests/test_video_flow.py)
SMALL_FLAGS = ["--flow-scale", "1.0"]


def _tacest(*args):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def seqdir(tmp_path_factory):
    seq = generate(SynthConfig(width=320, height=240, n_frames=60, seed=11, events=[(15, 40, 30.0, 120.0)]))
    out = tmp_path_factory.mktemp("cli")
    return seq, write_sequence(seq, out)


def _record(paths, out, *extra, frames=None):
    return _tacest("record", "--source", "video", "--frames", frames or paths["frames"], "--calib", paths["calib"],
                   "--finger-log", paths["finger_log"], "-o", out, *SMALL_FLAGS, *extra)


def test_cli_writes_a_valid_run(seqdir, tmp_path):
    seq, paths = seqdir
    out = tmp_path / "run.h5"
    p = _record(paths, out)
    assert p.returncode == 0, p.stderr
    assert "wrote" in p.stderr
    run = read_run(out)  # validates against SPEC
    assert run.source == "video" and run.dim == 3 and run.n_fingers == 1
    assert run.finger_position.shape == (60, 1, 3) and run.force is None
    assert run.finger_radius[0] == pytest.approx(seq.calib.finger_radius)
    c = run.contact[:, 0].astype(bool)
    truth = seq.contact.astype(bool)
    assert c[17:38].all() and not c[:13].any() and not c[43:].any()
    ang = np.degrees(np.arccos(np.clip(np.sum(run.normal[c & truth, 0] * seq.normal[c & truth], 1), -1, 1)))
    assert np.median(ang) < 5.0  # the target
    assert "video_settings" in run.extra_attrs and "dome_calibration" in run.extra_attrs


def test_cli_video_file_and_fps(seqdir, tmp_path):
    seq, _ = seqdir
    paths = write_sequence(seq, tmp_path, video=True)  # MJPG .avi, 30 fps, frames at t = k / 30
    out = tmp_path / "run.h5"
    p = _record(paths, out)
    assert p.returncode == 0, p.stderr
    run = read_run(out)
    assert run.n_samples == 60 and run.dt == pytest.approx(1 / 30)
    assert run.contact[17:38, 0].all()
    # --fps overrides the container's rate: frames at k / 60 s, the finger log still covers them
    p = _record(paths, tmp_path / "r60.h5", "--fps", "60")
    assert p.returncode == 0, p.stderr
    assert read_run(tmp_path / "r60.h5").dt == pytest.approx(1 / 60)


def _one_line_error(p, *needles):
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("tacest: error:")
    for n in needles:
        assert n in lines[0], lines[0]


def test_cli_errors_are_one_line(seqdir, tmp_path):
    seq, paths = seqdir
    out = tmp_path / "x.h5"
    # missing folder (click checks existence)
    _one_line_error(_record(paths, out, frames=tmp_path / "nope"), "nope")
    # unreadable image
    bad = tmp_path / "bad"
    bad.mkdir()
    for k in range(3):
        (bad / f"f{k}.png").write_bytes(b"not a png")
    _one_line_error(_record(paths, out, "--fps", "30", frames=bad), "f0.png", "cannot read image")
    # a folder without timestamps.csv and no --fps
    _one_line_error(_record(paths, out, frames=bad), "--fps")
    # frames and finger log on different clocks
    late = tmp_path / "late.csv"
    late.write_text("t,x,y,z\n1000,0,0,0\n1001,0,0,0\n")
    _one_line_error(_tacest("record", "--source", "video", "--frames", paths["frames"], "--calib", paths["calib"],
                            "--finger-log", late, "-o", out), "overlap")
    # calibration without a required key
    cal = tmp_path / "cal.json"
    cal.write_text('{"image_size": [320, 240], "center_px": [160, 120], "dome_radius_m": 0.01}')
    _one_line_error(_tacest("record", "--source", "video", "--frames", paths["frames"], "--calib", cal,
                            "--finger-log", paths["finger_log"], "-o", out), "rim_radius_px")
    # calibration for another image size
    cal.write_text('{"image_size": [640, 480], "center_px": [320, 240], "rim_radius_px": 200, '
                   '"dome_radius_m": 0.01, "rotation_world_from_finger": [[1,0,0],[0,1,0],[0,0,1]]}')
    _one_line_error(_tacest("record", "--source", "video", "--frames", paths["frames"], "--calib", cal,
                            "--finger-log", paths["finger_log"], "-o", out), "320x240", "640x480")
    # missing video options
    _one_line_error(_tacest("record", "--source", "video", "-o", out), "--frames")
    assert not out.exists()


def test_cli_reference_image_and_quiet(seqdir, tmp_path):
    seq, paths = seqdir
    out = tmp_path / "run.h5"
    p = _record(paths, out, "--reference", paths["frames"] / "frame_00000.png", "--quiet")
    assert p.returncode == 0 and p.stderr == ""
    assert read_run(out).contact[17:38, 0].all()


def test_synth_module_command(tmp_path):
    p = subprocess.run([sys.executable, "-m", "tacest.sensors.synth_tactile", tmp_path / "s", "--frames", "12",
                        "--size", "160x120", "--dim", "2"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    names = sorted(x.name for x in (tmp_path / "s").iterdir())
    assert names == ["calib.json", "fingers.csv", "frames", "truth.csv"]
    assert len(list((tmp_path / "s" / "frames").glob("*.png"))) == 12
    assert (tmp_path / "s" / "fingers.csv").read_text().startswith("t,x,y\n")
    assert (tmp_path / "s" / "truth.csv").read_text().startswith("t,contact,nx,ny,u,v\n")
