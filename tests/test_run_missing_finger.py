"""The per-finger missing mask of run files (``/quality/missing_finger``, docs/formats.md):
round trip, default from ``/quality/missing``, and what the reader rejects."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tacest.errors import FileFormatError
from tacest.io.run import Run, read_run, write_run


def two_finger_run(T=10) -> Run:
    fp = np.zeros((T, 2, 2))
    fp[:, 1, 0] = 0.1
    return Run(dim=2, dt=0.01, time=np.arange(T) * 0.01, gravity=np.array([0.0, -9.81]), source="test",
               finger_position=fp, finger_radius=np.array([0.01, 0.01]), contact=np.zeros((T, 2), np.uint8),
               normal=np.full((T, 2, 2), np.nan))


def test_round_trip_and_mask(tmp_path):
    run = two_finger_run()
    mf = np.zeros((10, 2), np.uint8)
    mf[3, 1] = 1
    mf[6] = 1
    run.missing_finger, run.missing = mf, mf.any(axis=1).astype(np.uint8)
    write_run(run, tmp_path / "r.h5")
    back = read_run(tmp_path / "r.h5")
    np.testing.assert_array_equal(back.missing_finger, mf)
    np.testing.assert_array_equal(back.missing, [0, 0, 0, 1, 0, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(back.finger_missing_mask, mf.astype(bool))


def test_mask_defaults_from_the_per_sample_mask_or_to_none_missing():
    run = two_finger_run()
    assert run.finger_missing_mask.shape == (10, 2) and not run.finger_missing_mask.any()
    run.missing = np.zeros(10, np.uint8)
    run.missing[4] = 1
    expect = np.zeros((10, 2), bool)
    expect[4] = True
    np.testing.assert_array_equal(run.finger_missing_mask, expect)


def test_a_file_without_the_new_dataset_still_reads(tmp_path):
    run = two_finger_run()
    run.missing = np.zeros(10, np.uint8)
    write_run(run, tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5") as f:
        assert "missing_finger" not in f["quality"]
    assert read_run(tmp_path / "r.h5").missing_finger is None


def _write_raw(path, mf, missing):
    run = two_finger_run()
    write_run(run, path)
    with h5py.File(path, "a") as f:
        g = f.require_group("quality")
        if missing is not None:
            g.create_dataset("missing", data=missing)
        if mf is not None:
            g.create_dataset("missing_finger", data=mf)


@pytest.mark.parametrize("mf,missing,where,what", [
    (np.zeros((10, 3)), np.zeros(10), "/quality/missing_finger", "shape"),
    (np.full((10, 2), 0.5), np.zeros(10), "/quality/missing_finger", "0 or 1"),
    (np.eye(10, 2), None, "/quality/missing", "required"),
    (np.eye(10, 2), np.zeros(10), "/quality/missing", "sample 0 disagrees"),
    (np.zeros((10, 2)), np.eye(1, 10, 7).ravel(), "/quality/missing", "sample 7 disagrees"),
])
def test_bad_masks_are_rejected_naming_the_path(tmp_path, mf, missing, where, what):
    path = tmp_path / "bad.h5"
    _write_raw(path, mf, missing)
    with pytest.raises(FileFormatError) as exc:
        read_run(path)
    msg = str(exc.value)
    assert where in msg and what in msg and "bad.h5" in msg


def test_writer_refuses_an_inconsistent_mask(tmp_path):
    run = two_finger_run()
    run.missing_finger = np.eye(10, 2, dtype=np.uint8)
    with pytest.raises(FileFormatError, match="/quality/missing"):
        write_run(run, tmp_path / "r.h5")
    assert not (tmp_path / "r.h5").exists()


def test_the_starting_shapes_ignore_a_missing_fingers_placeholders():
    """A finger's placeholder samples (/quality/missing_finger, contact 0 there) are
    neither touching nor not touching for the 2-D starting-shape score: a placeholder
    inside the object costs nothing, the same sample of a finger whose data arrived does."""
    from tacest.estimation.initial import touch_inconsistency_batch

    run = two_finger_run()
    run.finger_position[:, 1] = [0.0, 0.0]  # finger 1 at the centre of the box below: inside
    run.finger_position[:, 0] = [0.5, 0.0]  # finger 0 far outside, not touching: no cost
    V = np.array([[[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]])
    poses = np.zeros((1, 10, 3))
    mf = np.zeros((10, 2), np.uint8)
    mf[:, 1] = 1  # finger 1's data never arrived
    run.missing_finger, run.missing = mf, mf.any(axis=1).astype(np.uint8)
    assert touch_inconsistency_batch(run, V, poses)[0] == 0.0
    mf[4, 1] = 0  # ... except at sample 4, where it reads "not touching" from inside
    run.missing_finger = mf
    # the fingertip (radius 0.01) overlaps the box by 0.06 m: 0.06² m²
    assert touch_inconsistency_batch(run, V, poses)[0] == pytest.approx(0.06**2, rel=1e-9)
