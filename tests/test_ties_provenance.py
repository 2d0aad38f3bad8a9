"""Files are tied to what they came from by SHA-256 (issue 27, item 3), and every output
says which tacest and which command line wrote it (item 6)."""

import json
import shlex
from pathlib import Path

import h5py
import numpy as np
import pytest

from tacest import __version__
from tacest.io.h5util import sha256_file
from tacest.io.plan import read_plan, runs_sha256
from tacest.io.run import read_run, write_run
from tacest.provenance import sha256_text
from tacest.sim.record import SimOptions, record_sim
from tests.reliability_files import make_run, one_error_line, poke_plan, tacest, truth_estimate


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("ties")
    a = make_run(d / "a.h5", seed=1, pokes=2)
    # another run of the same length: the same recording with one force sample changed
    other = read_run(a)
    other.force = other.force.copy()
    other.force[5, 0, 0] += 0.01
    write_run(other, d / "b.h5")
    est = truth_estimate([a], d / "est.h5")
    return {"dir": d, "a": a, "b": d / "b.h5", "est": est}


# ---------------------------------------------------------------------------------
# item 3: ties


def test_plan_refuses_runs_the_estimate_was_not_made_from(files, tmp_path):
    assert read_run(files["a"]).n_samples == read_run(files["b"]).n_samples
    res = tacest("plan", files["est"], files["b"], "-o", tmp_path / "plan.h5")
    assert res.returncode == 2
    line = one_error_line(res)
    assert str(files["b"]) in line and "source_sha256" in line and "/runs/0" in line
    assert not (tmp_path / "plan.h5").exists()


def test_plan_records_the_runs_it_was_made_from(files, tmp_path):
    out = tmp_path / "plan.h5"
    res = tacest("plan", files["est"], files["a"], "--iterations", "1", "--population", "3", "-o", out, "--quiet")
    assert res.returncode == 0, res.stderr
    plan = read_plan(out)
    assert runs_sha256(plan) == [sha256_file(files["a"])]
    assert plan.estimate_sha256 == sha256_file(files["est"])
    with h5py.File(out) as f:
        assert f.attrs["tacest_version"] == __version__
        assert f.attrs["command_line"].startswith("tacest plan ")


def test_record_refuses_to_continue_another_run_with_a_plan(files, tmp_path):
    plan = poke_plan(tmp_path / "plan.h5", [files["a"]], files["est"])
    target = tmp_path / "b.h5"
    target.write_bytes(files["b"].read_bytes())
    res = tacest("record", "--plan", plan, "-o", target)
    assert res.returncode == 2
    line = one_error_line(res)
    assert str(plan) in line and str(target) in line and "runs_sha256" in line
    assert target.read_bytes() == files["b"].read_bytes()


def test_record_continues_the_run_the_plan_was_made_from(files, tmp_path):
    target = tmp_path / "a.h5"
    target.write_bytes(files["a"].read_bytes())
    plan = poke_plan(tmp_path / "plan.h5", [target], files["est"])
    res = tacest("record", "--plan", plan, "-o", target, "--quiet")
    assert res.returncode == 0, res.stderr
    assert read_run(target).n_samples > read_run(files["a"]).n_samples
    entries = json.loads(h5py.File(target, "r").attrs["sim_options"])
    assert len(entries) == 2 and entries[1]["plan"]["sha256"] == sha256_file(plan)
    assert entries[1]["start_sample"] == read_run(files["a"]).n_samples - 1


# ---------------------------------------------------------------------------------
# item 6: provenance


def test_a_recorded_run_can_be_reproduced_from_its_file(tmp_path):
    out = tmp_path / "run.h5"
    args = ["record", "--object", "polygon:5", "--seed", "7", "--pokes", "2", "--effect", "latency:samples=1",
            "--noise-force", "0.03", "-o", out]
    res = tacest(*args)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        assert f.attrs["tacest_version"] == __version__
        assert shlex.split(f.attrs["command_line"]) == ["tacest", *map(str, args)]
        (entry,) = json.loads(f.attrs["sim_options"])
    assert entry["options"]["seed"] == 7 and entry["options"]["effects"] == ["latency:samples=1"]
    again = record_sim(SimOptions(**entry["options"]))
    run = read_run(out)
    for name in ("time", "finger_position", "contact", "force"):
        assert np.array_equal(getattr(again, name), getattr(run, name)), name
    assert np.array_equal(again.truth.pose, run.truth.pose)


def test_a_recorded_3d_run_can_be_reproduced_from_its_file(tmp_path):
    """The 3-D recorder notes its options too; the dimension registry records them again."""
    from tacest.dims import record_sim as record_any

    out = tmp_path / "run3.h5"
    res = tacest("record", "--dim", "3", "--seed", "3", "--pokes", "1", "-o", out)
    assert res.returncode == 0, res.stderr
    with h5py.File(out) as f:
        (entry,) = json.loads(f.attrs["sim_options"])
    assert entry["options"]["dim"] == 3 and entry["options"]["seed"] == 3
    again = record_any(SimOptions(**entry["options"]))
    run = read_run(out)
    assert np.array_equal(again.finger_position, run.finger_position)
    assert np.array_equal(again.truth.pose, run.truth.pose)


def test_a_blind_run_keeps_its_answer_to_itself(tmp_path):
    out = tmp_path / "hidden.h5"
    args = ["record", "--seed", "2", "--pokes", "1", "--effect", "latency:samples=2", "--no-truth", "-o", out]
    assert tacest(*args).returncode == 0
    with h5py.File(out) as f:
        attrs = dict(f.attrs)
    assert "command_line" not in attrs and "sim_options" not in attrs
    assert not any("latency" in str(v) for v in attrs.values())
    assert attrs["command_line_sha256"] == sha256_text(shlex.join(["tacest", *map(str, args)]))
    assert len(attrs["sim_options_sha256"]) == 64


def test_estimate_and_diagnosis_record_version_and_command_line(files, tmp_path, monkeypatch, capsys):
    import tacest.dims as dims
    from tacest.cli import diagnose as diagnose_cli
    from tacest.cli.main import main
    from tacest.io.estimate import read_estimate

    est = read_estimate(files["est"])
    monkeypatch.setattr(dims, "estimate_runs", lambda *a, **k: est)
    out = tmp_path / "est.h5"
    with pytest.raises(SystemExit) as exc:
        main(["estimate", str(files["a"]), "-o", str(out), "--quiet"])
    assert exc.value.code == 0
    with h5py.File(out) as f:
        assert f.attrs["tacest_version"] == __version__
        assert f.attrs["command_line"] == shlex.join(["tacest", "estimate", str(files["a"]), "-o", str(out),
                                                      "--quiet"])

    class Diag:
        verdict, reason = "none", "a stand-in"

        def to_json(self):
            return {"verdict": self.verdict, "effects": [], "where": []}

    written = {}

    def write(diag, folder, obj):
        written["obj"] = obj
        return []

    diagnose_cli._report(Diag(), write, tmp_path / "r", as_json=True, quiet=True)
    printed = json.loads(capsys.readouterr().out)
    assert printed == written["obj"]
    assert printed["tacest_version"] == __version__ and "command_line" in printed


def test_the_defaults_ship_with_the_package_and_match_the_code(tmp_path):
    from tacest.cli.config import defaults_toml
    from tacest.estimation.config import EstimatorConfig, load_config

    res = tacest("config", "--defaults", cwd=tmp_path)  # no checkout around: the installed package's
    assert res.returncode == 0 and res.stdout == defaults_toml()
    (tmp_path / "defaults.toml").write_text(res.stdout)
    assert load_config(tmp_path / "defaults.toml") == EstimatorConfig()


def test_source_digest_names_the_code_version_a_benchmark_result_belongs_to(tmp_path, monkeypatch):
    """tacest.provenance.source_digest: the same code gives the same digest; an edit to
    an extra file (a benchmark script) or to any package source gives another (edited
    in a copy of the package that stands in for it), and compiled caches do not count."""
    import shutil

    import tacest
    from tacest.provenance import source_digest

    script = tmp_path / "bench.py"
    script.write_text("A = 1\n")
    first = source_digest(script)
    assert first == source_digest(script) and len(first) == 12
    script.write_text("A = 2\n")
    assert source_digest(script) != first
    assert source_digest() != source_digest(script)

    copy = tmp_path / "tacest"
    shutil.copytree(Path(tacest.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(tacest, "__file__", str(copy / "__init__.py"))
    before = source_digest()
    (copy / "__pycache__").mkdir(exist_ok=True)
    (copy / "__pycache__" / "x.py").write_text("ignored = True\n")
    assert source_digest() == before
    target = copy / "diagnosis" / "diagnose.py"
    target.write_text(target.read_text().replace("FLOOR_SIGMAS = 2.0", "FLOOR_SIGMAS = 2.5"))
    assert source_digest() != before
