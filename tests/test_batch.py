"""tacest estimate --batch (tacest.batch, issue 29 item 4): manifests (CSV, TOML) and
their errors (one line, exit 2, before any work), one estimate per object and a summary
(CSV and JSON) with every failed object and its reason, an output written at once.

The estimates here come from a stand-in of the estimator (the truth of each run as the
estimate, in milliseconds); tests/test_parallel.py runs real batches on a cluster."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner

from tacest.batch import SUMMARY_COLUMNS, read_manifest
from tacest.errors import SolveFailedError, TacestError
from tests.reliability_files import make_run, one_error_line, tacest


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    return {name: make_run(d / f"{name}.h5", seed=seed, pokes=2) for name, seed in
            (("a1", 1), ("a2", 2), ("b1", 3), ("c1", 4))}


def _truth_estimate(runs, shape_spec="box", config=None, method="implicit"):
    from tacest.io.estimate import Estimate, RunEstimate

    tr = runs[0].truth
    if tr.mass > 10:  # never: a reachable failure is made by the test below
        raise SolveFailedError("x")
    return Estimate(dim=2, shape=shape_spec, vertices=tr.vertices,
                    params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                            "friction_finger": tr.friction_finger},
                    runs=[RunEstimate(pose=r.truth.pose, velocity=np.zeros_like(r.truth.pose),
                                      source_file=r.filename or "") for r in runs],
                    solver_status="Solve_Succeeded", success=True, iterations=7, objective=1.5)


@pytest.fixture
def stand_in(monkeypatch):
    import tacest.dims

    monkeypatch.setattr(tacest.dims, "estimate_runs", _truth_estimate)


def test_csv_and_toml_manifests_name_the_same_objects(runs, tmp_path):
    (tmp_path / "m.csv").write_text(f"object,run,shape\nA,{runs['a1']},polygon:6\nA,{runs['a2']},polygon:6\n"
                                    f"\nB,{runs['b1']},\n")
    (tmp_path / "m.toml").write_text(f'[objects.A]\nruns = ["{runs["a1"]}", "{runs["a2"]}"]\nshape = "polygon:6"\n'
                                     f'[objects.B]\nruns = ["{runs["b1"]}"]\n')
    for m in ("m.csv", "m.toml"):
        objs = read_manifest(tmp_path / m)
        assert [o.name for o in objs] == ["A", "B"]
        assert objs[0].runs == (str(runs["a1"]), str(runs["a2"])) and objs[0].shape == "polygon:6"
        assert objs[1].shape is None
    # paths are relative to the manifest's folder
    (runs["a1"].parent / "rel.csv").write_text("object,run\nA,a1.h5\n")
    assert read_manifest(runs["a1"].parent / "rel.csv")[0].runs == (str(runs["a1"]),)


@pytest.mark.parametrize("text, message", [
    ("object,file\nA,{a1}\n", "header must name"),
    ("object,run\n", "lists no object"),
    ("object,run\nA,{a1}\nB,{a1}\n", "listed twice"),
    ("object,run\nA,{a1}\nA,{a1}\n", "listed twice"),
    ("object,run\nA,/no/such/run.h5\n", "does not exist"),
    ("object,run\n../up,{a1}\n", "cannot name a file"),
    ("object,run\nA,\n", "needs an object and a run"),
    ("object,run,shape\nA,{a1},box\nA,{a2},polygon:6\n", "two shapes"),
    ("object,run\nA,{a1},extra\n", "3 fields for 2 columns"),
])
def test_a_bad_csv_manifest_is_one_line(runs, tmp_path, text, message):
    m = tmp_path / "m.csv"
    m.write_text(text.format(**{k: str(v) for k, v in runs.items()}))
    with pytest.raises(TacestError, match=message) as exc:
        read_manifest(m)
    assert str(m) in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("text, message", [
    ('[objects.A]\nruns = "{a1}"\n', "must be a list"),
    ('[objects.A]\nruns = ["{a1}"]\ncolour = "red"\n', "unknown key 'colour'"),
    ('shape = "box"\n', "tables only"),
    ('[objects.A]\nruns = []\n', "has no run file"),
    ('[objects.A\n', "not a valid TOML"),
])
def test_a_bad_toml_manifest_is_one_line(runs, tmp_path, text, message):
    m = tmp_path / "m.toml"
    m.write_text(text.format(**{k: str(v) for k, v in runs.items()}))
    with pytest.raises(TacestError, match=message):
        read_manifest(m)


def test_bad_manifest_through_the_cli_exits_2_before_any_work(runs, tmp_path):
    m = tmp_path / "m.txt"
    m.write_text("A a1.h5\n")
    line = one_error_line(tacest("estimate", "--batch", m, "-o", tmp_path / "out"))
    assert "a .csv or a .toml" in line
    m = tmp_path / "m.csv"
    m.write_text("object,run\nA,missing.h5\n")
    line = one_error_line(tacest("estimate", "--batch", m, "-o", tmp_path / "out"))
    assert "missing.h5" in line and "does not exist" in line
    assert not (tmp_path / "out").exists()
    res = tacest("estimate", str(runs["a1"]), "--batch", m, "-o", tmp_path / "out")
    assert res.returncode == 2 and "not both" in res.stderr
    res = tacest("estimate", str(runs["a1"]), "--workers", "2", "-o", tmp_path / "e.h5")
    assert res.returncode == 2 and "go with --batch" in res.stderr


def test_a_batch_writes_every_object_and_lists_the_failed_ones(runs, tmp_path, stand_in):
    from tacest.cli.estimate import estimate as cmd
    from tacest.io.estimate import read_estimate

    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"not an HDF5 file")
    m = tmp_path / "objects.csv"
    m.write_text(f"object,run\nA,{runs['a1']}\nA,{runs['a2']}\nbroken,{broken}\nC,{runs['c1']}\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(cmd, ["--batch", str(m), "-o", str(out), "--quiet"])
    # an object failed: a TacestError (main: one line, exit 2), after writing
    assert isinstance(res.exception, TacestError), res.output
    assert "1 of 3 object(s) failed, first broken" in str(res.exception)
    assert sorted(p.name for p in out.iterdir()) == ["A.h5", "C.h5", "summary.csv", "summary.json"]
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["object"] for r in rows] == ["A", "broken", "C"]  # the manifest's order, none dropped
    assert list(rows[0]) == list(SUMMARY_COLUMNS)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert "broken.h5" in rows[1]["reason"] and rows[1]["estimate"] == "" and rows[0]["runs"] == "2"
    obj = json.loads((out / "summary.json").read_text())
    assert obj["ok"] == 2 and obj["failed"] == 1 and obj["objects"][1]["status"] == "failed"
    assert obj["objects"][0]["mass"] == pytest.approx(read_estimate(out / "A.h5").params["mass"])
    est = read_estimate(out / "A.h5")
    assert len(est.runs) == 2 and est.runs[0].source_file == str(runs["a1"])
    # every object fine: exit 0, the earlier output replaced whole
    m.write_text(f"object,run\nC,{runs['c1']}\n")
    res = CliRunner().invoke(cmd, ["--batch", str(m), "-o", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == ["C.h5", "summary.csv", "summary.json"]


def test_a_batch_never_replaces_a_folder_that_is_not_its_output(runs, tmp_path, stand_in):
    from tacest.cli.estimate import estimate as cmd

    out = tmp_path / "mine"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    m = tmp_path / "objects.csv"
    m.write_text(f"object,run\nC,{runs['c1']}\n")
    res = CliRunner().invoke(cmd, ["--batch", str(m), "-o", str(out), "--quiet"])
    assert res.exit_code != 0 and (out / "keep.txt").read_text() == "x" and len(list(out.iterdir())) == 1
