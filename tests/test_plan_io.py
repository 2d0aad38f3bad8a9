"""Plan files (SPEC tacest.plan): round trip, files from other writers, validation."""

import h5py
import numpy as np
import pytest

from tacest.errors import FileFormatError, TacestError
from tacest.io.plan import POKE_NAMES, Plan, read_plan, write_plan


def _plan(**kw):
    rng = np.random.default_rng(0)
    cand = rng.normal(size=(5, 6))
    base = dict(chosen=cand[2], candidates=cand, scores=rng.normal(size=5), method="eig", score="logdet",
                estimate_sha256="ab" * 32)
    base.update(kw)
    return Plan(**base)


def test_round_trip(tmp_path):
    p = tmp_path / "plan.h5"
    plan = _plan(extra_attrs={"config": "{}"})
    write_plan(plan, p)
    back = read_plan(p)
    assert np.array_equal(back.chosen, plan.chosen)
    assert np.array_equal(back.candidates, plan.candidates)
    assert np.array_equal(back.scores, plan.scores)
    assert (back.method, back.score, back.estimate_sha256) == ("eig", "logdet", "ab" * 32)
    assert back.names == list(POKE_NAMES) and back.kind == "poke"
    assert back.extra_attrs == {"config": "{}"}
    assert back.chosen_dict()["approach_angle"] == plan.chosen[1]
    with h5py.File(p, "r") as f:  # the SPEC layout
        assert f["candidates/params"].shape == (5, 6) and f["candidates/score"].shape == (5,)
        assert f["chosen/params"].shape == (6,)
        assert set(f.attrs) >= {"method", "score", "estimate_sha256"}


def test_plan_from_another_writer_minimal(tmp_path):
    # only what SPEC lists: no format/version/names/kind/estimate_sha256
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("candidates/params", data=np.zeros((0, 6)))
        f.create_dataset("candidates/score", data=np.zeros(0))
        f.create_dataset("chosen/params", data=np.array([0, 1.0, 0, 0.03, 0.01, 0.02]))
        f.attrs["method"] = "random"
        f.attrs["score"] = "D"
    back = read_plan(p)
    assert back.names == list(POKE_NAMES) and back.estimate_sha256 == ""
    assert back.candidates.shape == (0, 6)


def test_custom_action_names(tmp_path):
    p = tmp_path / "plan.h5"
    write_plan(_plan(chosen=np.ones(3), candidates=np.ones((2, 3)), scores=np.ones(2),
                     names=["a", "b", "c"], kind="push"), p)
    back = read_plan(p)
    assert back.names == ["a", "b", "c"] and back.kind == "push"


@pytest.mark.parametrize("mutate,where", [
    (lambda f: f["chosen/params"].attrs.__setitem__("names", np.array(["a", "b"], dtype=object)),
     "/chosen/params attrs names"),
    (lambda f: (f.__delitem__("candidates/score"), f.create_dataset("candidates/score", data=np.ones(3))),
     "/candidates/score"),
    (lambda f: (f.__delitem__("chosen/params"), f.create_dataset("chosen/params", data=[0, np.nan, 0, 0, 0, 0])),
     "/chosen/params"),
    (lambda f: f.attrs.__delitem__("method"), "attrs method"),
    (lambda f: f.attrs.__setitem__("format", "tacest.run"), "attrs format"),
    (lambda f: f.attrs.__setitem__("version", 7), "attrs version"),
    (lambda f: f.__delitem__("candidates/params"), "/candidates/params"),
])
def test_bad_files_name_file_and_path(tmp_path, mutate, where):
    p = tmp_path / "bad.h5"
    write_plan(_plan(), p)
    with h5py.File(p, "a") as f:
        mutate(f)
    with pytest.raises(FileFormatError) as exc:
        read_plan(p)
    assert str(p) in str(exc.value) and where in str(exc.value)


def test_not_a_plan(tmp_path):
    with pytest.raises(TacestError, match="no such file"):
        read_plan(tmp_path / "missing.h5")
    bad = tmp_path / "text.h5"
    bad.write_text("hello")
    with pytest.raises(TacestError, match="not a readable HDF5"):
        read_plan(bad)


def test_write_validates_and_is_atomic(tmp_path):
    p = tmp_path / "plan.h5"
    with pytest.raises(FileFormatError, match="/candidates/params"):
        write_plan(_plan(candidates=np.zeros((3, 4))), p)
    assert not p.exists() and list(tmp_path.iterdir()) == []
