"""Tactile flow analysis and the video recorder in process (small synthetic sequences)."""

import csv

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.io.run import read_run
from tacest.sensors.synth_tactile import SynthConfig, generate, write_sequence
from tacest.sensors.tactile_flow import DetectSettings, FlowSettings, TactileFlow, decide_contacts
from tacest.sensors.video import VideoOptions, read_finger_log, record_video

#: Test sequences are 320 x 240 (4x fewer pixels than the real 640 x 480) analysed at
#: full resolution: the dots then have the same size in the flow's input as 640 x 480 at
#: the default work_scale 0.5.
SMALL = dict(width=320, height=240)
SMALL_FLOW = FlowSettings(work_scale=1.0)
SMALL_OPTS = dict(flow=SMALL_FLOW)


def _angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def seq3():
    return generate(SynthConfig(**SMALL, n_frames=100, seed=1, dim=3))


def test_contact_detection_and_location_on_noisy_sequence(seq3):
    """Noise, lighting drift, shear and shading on: contacts found, normals close."""
    tf = TactileFlow(seq3.calib, SMALL_FLOW)
    tf.set_reference(seq3.frames[0])
    res = [tf.analyse(f) for f in seq3.frames]
    dec = decide_contacts([r.strength for r in res])
    truth = seq3.contact.astype(bool)
    tp = np.sum(dec.contact & truth)
    f1 = 2 * tp / (dec.contact.sum() + truth.sum())
    # F1: the benchmark's target is 0.95 on 640x480; allow one missed ramp frame per
    # contact here (3 contacts in 49 frames -> F1 >= 0.96), so 0.93 with margin
    assert f1 >= 0.93
    both = dec.contact & truth
    uv = np.array([r.uv for r in res])[both]
    # location: the source's centroid; 3 px = the scale at which the 8-px analysis grid
    # resolves a centroid (3/8 cell), i.e. 2.5 deg of polar angle on this 110-px dome
    assert np.median(np.linalg.norm(uv - seq3.contact_uv[both], axis=1)) < 3.0
    n = seq3.calib.object_normal(uv)[0]
    assert np.median(_angles_deg(n, seq3.normal[both])) < 5.0  # the target


def test_no_contact_no_detection():
    """Only noise and lighting drift: nothing is flagged."""
    seq = generate(SynthConfig(**SMALL, n_frames=40, seed=3, events=[]))
    tf = TactileFlow(seq.calib, SMALL_FLOW)
    tf.set_reference(seq.frames[0])
    dec = decide_contacts([tf.analyse(f).strength for f in seq.frames])
    assert not dec.contact.any()


def test_hhd_keeps_shear_out_of_the_contact_signal():
    """A pure translation of the gel (shear without indentation) gives no contact."""
    import cv2

    seq = generate(SynthConfig(**SMALL, n_frames=2, seed=4, events=[], noise_sigma=0, drift_gain=0,
                               drift_offset=0, gradient=0))
    tf = TactileFlow(seq.calib, SMALL_FLOW)
    tf.set_reference(seq.frames[0])
    shifted = cv2.warpAffine(seq.frames[0], np.float32([[1, 0, 2.0], [0, 1, -1.0]]), (320, 240),
                             borderMode=cv2.BORDER_REPLICATE)
    a = tf.analyse(shifted)
    assert a.strength < DetectSettings().min_strain  # below the on-threshold floor
    # the translation is in the harmonic part (0.3 px: DIS accuracy at a 2-px shift on dots)
    assert np.allclose(a.shear, [2.0, -1.0], atol=0.3)


def test_hysteresis_and_noise_level():
    s = np.array([0.0, 0.01, 0.012, 0.008, 0.01, 0.05, 0.025, 0.021, 0.015, 0.05, 0.005])
    d = decide_contacts(s, DetectSettings(noise_frames=4, k_on=4, k_off=2, min_strain=0.0))
    # noise = median(0.01, 0.012, 0.008, 0.01) = 0.01 -> on above 0.04, off below 0.02
    assert d.noise == pytest.approx(0.01)
    assert d.contact.tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 0, 1, 0]
    # clean images: the floor keeps flicker out
    d = decide_contacts(np.full(20, 1e-4), DetectSettings(min_strain=0.02))
    assert d.threshold_on == 0.02 and not d.contact.any()


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Hand-built contacts: at the apex (frames 14-29) and 45 deg off it towards +u
    (frames 45-64), low noise; 3-D, finger pointing down (synth_tactile.ROTATION_3D)."""
    seq = generate(SynthConfig(**SMALL, n_frames=80, seed=5, events=[(14, 30, 0.0, 0.0), (45, 65, 45.0, 0.0)]))
    out = tmp_path_factory.mktemp("vid")
    return seq, write_sequence(seq, out)


def test_record_normal_sign_and_direction(written, tmp_path):
    seq, paths = written
    run, res = record_video(paths["frames"], paths["calib"], paths["finger_log"], output=tmp_path / "r.h5", options=VideoOptions(**SMALL_OPTS))
    run = read_run(tmp_path / "r.h5")
    assert run.source == "video" and run.dim == 3 and run.force is None
    c = run.contact[:, 0].astype(bool)
    # contact on the full-depth frames of both presses (ramps may be missed)
    assert c[16:28].all() and c[47:63].all() and not c[:13].any() and not c[31:44].any()
    n = run.normal[:, 0]
    assert np.all(np.isnan(n[~c]))
    # apex: object normal = minus the finger axis (world -z) = world +z.  4 deg = 5 px on
    # this 110-px dome, comfortably above the ~1-2 px location error
    assert np.all(_angles_deg(n[16:28], np.array([0, 0, 1.0])) < 4.0)
    # 45 deg towards +u: fingertip normal (s, 0, s) in the finger frame -> world (s, 0, -s);
    # object normal (-s, 0, s) (hand-computed; see tests/test_video_dome.py)
    s = np.sqrt(0.5)
    assert np.median(_angles_deg(n[47:63], np.array([-s, 0, s]))) < 4.0


def test_record_time_matching(written, tmp_path):
    seq, paths = written
    # a finger log that starts 0.4 s after the first frame, at 250 Hz, with a known path
    t = np.arange(0.4, 3.5, 0.004)
    pos = np.stack([t, 2 * t, -t], 1)
    log = tmp_path / "log.csv"
    with open(log, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "z"])
        w.writerows([[f"{a:.6f}", *(f"{x:.6f}" for x in p)] for a, p in zip(t, pos)])
    run, _ = record_video(paths["frames"], paths["calib"], log,
                          options=VideoOptions(**SMALL_OPTS))
    # first sample = first frame at or after 0.4 s = frame 12 (t = 0.4 s at 30 Hz)
    assert run.time[0] == pytest.approx(12 / 30.0)
    assert run.n_samples == 80 - 12
    assert run.dt == pytest.approx(1 / 30.0)
    # positions interpolated onto the frame times (the path is linear: exact)
    assert np.allclose(run.finger_position[:, 0, 0], run.time, atol=1e-9)
    assert np.allclose(run.finger_position[:, 0, 1], 2 * run.time, atol=1e-9)


def test_record_2d_and_log_orientation(tmp_path):
    """2-D from an x,y log; orientation from qw,qx,qy,qz columns instead of the calibration."""
    from scipy.spatial.transform import Rotation

    seq = generate(SynthConfig(**SMALL, n_frames=50, seed=6, dim=2, events=[(14, 40, 45.0, 0.0)]))
    paths = write_sequence(seq, tmp_path)
    cal = seq.calib
    R = cal.rotation_world_from_finger
    cal.rotation_world_from_finger = None
    cal.save(paths["calib"])
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    with open(paths["finger_log"], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "qw", "qx", "qy", "qz"])
        for t in np.arange(-0.5, 2.5, 0.01):
            w.writerow([f"{t:.4f}", "0.1", "0.2", *(f"{x:.9f}" for x in q)])
    run, _ = record_video(paths["frames"], paths["calib"], paths["finger_log"], output=tmp_path / "r.h5", options=VideoOptions(**SMALL_OPTS))
    run = read_run(tmp_path / "r.h5")
    assert run.dim == 2 and run.finger_position.shape == (50, 1, 2)
    c = run.contact[:, 0].astype(bool)
    assert c[17:37].all()
    # finger axis world +x, contact 45 deg towards +u = world +y: object normal (-s, -s)
    s = np.sqrt(0.5)
    assert np.median(_angles_deg(run.normal[c, 0], np.array([-s, -s]))) < 4.0


def test_dropped_frame_is_marked_missing(written, tmp_path):
    seq, paths = written
    ts = paths["frames"] / "timestamps.csv"
    rows = ts.read_text().splitlines()
    sub = tmp_path / "frames"
    sub.mkdir()
    keep = [r for i, r in enumerate(rows) if i != 21]  # drop frame 20 (header is row 0)
    (sub / "timestamps.csv").write_text("\n".join(keep) + "\n")
    for r in keep[1:]:
        name = r.split(",")[0]
        (sub / name).symlink_to(paths["frames"] / name)
    run, _ = record_video(sub, paths["calib"], paths["finger_log"],
                          options=VideoOptions(**SMALL_OPTS))
    assert run.n_samples == 80 and run.missing is not None
    assert np.flatnonzero(run.missing).tolist() == [20]
    assert run.contact[20, 0] == 0 and np.all(np.isnan(run.normal[20, 0]))


def test_no_overlap_and_bad_logs(written, tmp_path):
    seq, paths = written
    late = tmp_path / "late.csv"
    late.write_text("t,x,y,z\n100,0,0,0\n101,0,0,0\n")
    with pytest.raises(TacestError, match="overlap in 0 frame"):
        record_video(paths["frames"], paths["calib"], late)
    for text, msg in [("t,x\n0,1\n1,2\n", "missing column 'y'"),
                      ("t,x,y,w\n0,1,2,3\n1,2,3,4\n", "unknown column 'w'"),
                      ("t,x,y\n0,1,2\n0,2,3\n", "strictly increasing"),
                      ("t,x,y\n0,1,2\n1,a,3\n", "line 3: not a number"),
                      ("t,x,y,finger\n0,1,2,0\n1,2,3,1\n", "several fingers"),
                      ("t,x,y,qw,qx,qy,qz\n0,1,2,1,0,0,0\n1,2,3,2,0,0,0\n", "not unit length")]:
        p = tmp_path / "bad.csv"
        p.write_text(text)
        with pytest.raises(TacestError, match=msg):
            read_finger_log(p)
