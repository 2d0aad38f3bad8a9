"""``tacest view``: the GIF opens with Pillow and has the frames asked for; the HTML holds
its data (frames, shapes, contacts with unit normals) and the inline renderer, and needs
nothing from the network."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.io.estimate import Estimate, RunEstimate, write_estimate
from tacest.io.run import write_run

TACEST = str(Path(sys.executable).parent / "tacest")


def _tacest(*args):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A short 2-D and a short 3-D simulated run with truth (one poke each)."""
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    d = tmp_path_factory.mktemp("view")
    out = {}
    for dim in (2, 3):
        run = record_sim(SimOptions(dim=dim, pokes=1, seed=5, object_spec="box"))
        path = d / f"run{dim}.h5"
        write_run(run, path)
        out[dim] = (path, run)
    return out


def _estimate_of(run, path):
    """An estimate file whose trajectory is the truth shifted by 1 cm along x and whose
    shape is the true one scaled by 1.1 (a view has to draw both)."""
    tr = run.truth
    pose = tr.pose.copy()
    pose[:, 0] += 0.01
    est = Estimate(dim=run.dim, shape="box", vertices=1.1 * tr.vertices,
                   params={"mass": 1.0, "inertia": tr.inertia, "friction_ground": 0.5, "friction_finger": 0.5},
                   runs=[RunEstimate(pose=pose, velocity=np.zeros((run.n_samples, 3 if run.dim == 2 else 6)),
                                     source_file=str(run.filename or ""))])
    write_estimate(est, path)
    return path


def _html_data(path):
    text = Path(path).read_text()
    m = re.search(r'<script type="application/json" id="tacest-data">(.*?)</script>', text, flags=re.S)
    assert m, "no data block"
    return text, json.loads(m.group(1))


def test_2d_run_gif_has_the_frames(runs, tmp_path):
    from PIL import Image

    path, run = runs[2]
    out = tmp_path / "run.gif"
    res = _tacest("view", path, "-o", out, "--fps", "10")
    assert res.returncode == 0, res.stderr
    # real time at 10 fps with dt = 0.01 s: every 10th sample, and the last one
    want = len(range(0, run.n_samples, 10)) + (0 if (run.n_samples - 1) % 10 == 0 else 1)
    assert f"{want} frames" in res.stderr
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == want
        im.seek(want // 2)
        px = np.asarray(im.convert("RGB"))
    assert px.std() > 10  # something is drawn


def test_2d_estimate_gif_with_run_and_max_frames(runs, tmp_path):
    from PIL import Image

    path, run = runs[2]
    est = _estimate_of(run, tmp_path / "est.h5")
    out = tmp_path / "est.gif"
    res = _tacest("view", est, "--run", path, "-o", out, "--max-frames", "12")
    assert res.returncode == 0, res.stderr
    with Image.open(out) as im:
        assert im.n_frames == 12


def test_2d_scene_draws_true_and_estimated_shapes(runs, tmp_path):
    from tacest.view.scene import load_scene

    path, run = runs[2]
    est = _estimate_of(run, tmp_path / "est.h5")
    sc = load_scene(est, run_path=path)
    assert sc.true_pose is not None and sc.est_pose is not None and sc.finger_position is not None
    assert "true shape, estimated shape, fingers, contacts, normals" in sc.title


def test_3d_html_holds_the_frames_shapes_and_contacts(runs, tmp_path):
    path, run = runs[3]
    est = _estimate_of(run, tmp_path / "est3.h5")
    out = tmp_path / "view.html"
    res = _tacest("view", est, "--run", path, "-o", out, "--fps", "20")
    assert res.returncode == 0, res.stderr
    text, data = _html_data(out)
    frames = data["frames"]
    want = len(range(0, run.n_samples, 5)) + (0 if (run.n_samples - 1) % 5 == 0 else 1)
    assert len(frames) == want and f"{want} frames" in res.stderr
    k = frames[10]["k"]
    np.testing.assert_allclose(frames[10]["truth"], run.truth.pose[k], atol=1e-6)
    np.testing.assert_allclose(frames[10]["est"][0], run.truth.pose[k, 0] + 0.01, atol=1e-6)
    assert len(data["est_shape"]["faces"]) == 12 and len(data["true_shape"]["vertices"]) == 8
    contacts = [c for f in frames for c in f["contacts"]]
    assert len(contacts) == sum(int(run.contact[f["k"]].sum()) for f in frames) > 0
    assert np.allclose(np.linalg.norm(np.array(contacts)[:, 3:], axis=1), 1.0, atol=1e-3)
    # self-contained: no script or style from elsewhere
    assert not re.search(r'<(script|link)[^>]+(src|href)=', text)
    assert "http" not in text.lower().replace("http-equiv", "")


def test_3d_run_without_estimate_and_wrong_suffixes(runs, tmp_path):
    path3, _ = runs[3]
    path2, _ = runs[2]
    res = _tacest("view", path3, "-o", tmp_path / "v.html")
    assert res.returncode == 0, res.stderr
    _, data = _html_data(tmp_path / "v.html")
    assert data["est_shape"] is None and data["true_shape"] is not None
    res = _tacest("view", path3, "-o", tmp_path / "v.gif")
    assert res.returncode == 2 and ".html" in res.stderr and "Traceback" not in res.stderr
    res = _tacest("view", path2, "-o", tmp_path / "v.html")
    assert res.returncode == 2 and ".gif or .mp4" in res.stderr
    res = _tacest("view", tmp_path / "none.h5", "-o", tmp_path / "v.gif")
    assert res.returncode == 2 and "none.h5" in res.stderr and len(res.stderr.strip().splitlines()) == 1
