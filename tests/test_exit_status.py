"""Exit statuses and the smaller reliability items (issue 27, items 4 and 5): a diagnosis
without held-out data, the same run twice, a missing linear solver, implausible values,
a bare ``tacest``, and a bug (status 3) told apart from bad input (status 2)."""

import h5py
import pytest

from tacest.cli.main import EXIT_BAD_INPUT, EXIT_BUG, EXIT_INTERRUPTED, EXIT_OK
from tests.reliability_files import make_run, one_error_line, tacest, truth_estimate


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("status")
    a = make_run(d / "a.h5", seed=1, pokes=1)
    return {"dir": d, "a": a, "est": truth_estimate([a], d / "est.h5")}


def test_the_statuses():
    assert (EXIT_OK, EXIT_BAD_INPUT, EXIT_BUG, EXIT_INTERRUPTED) == (0, 2, 3, 130)


def test_diagnose_without_held_out_data_cannot_decide(files, tmp_path):
    res = tacest("diagnose", files["a"], "-o", tmp_path / "report", "--json")
    assert res.returncode == 2 and res.stdout == ""  # no verdict a script could take for "none"
    line = one_error_line(res)
    assert "held-out data" in line and "several runs" in line and str(files["a"]) in line
    assert not (tmp_path / "report").exists()


def test_the_same_run_twice_is_refused(files, tmp_path):
    copy = tmp_path / "copy.h5"
    copy.write_bytes(files["a"].read_bytes())
    for args in (["estimate", files["a"], copy, "-o", tmp_path / "est.h5"],
                 ["diagnose", files["a"], files["a"], "-o", tmp_path / "report"]):
        res = tacest(*args)
        assert res.returncode == 2
        assert "same run" in one_error_line(res)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy.h5"]


def test_a_missing_linear_solver_is_named_before_any_work(files, tmp_path):
    config = tmp_path / "hsl.toml"
    config.write_text('[solver]\nlinear_solver = "ma57"\n')
    res = tacest("estimate", files["a"], "--config", config, "-o", tmp_path / "est.h5")
    assert res.returncode == 2
    line = one_error_line(res)
    assert "ma57" in line and "HSL" in line and "iterations" not in line
    assert not (tmp_path / "est.h5").exists()


@pytest.mark.parametrize("path,index,value,fragment", [
    ("tactile/force", (3, 0, 1), 1e30, "/tactile/force: 1e+30 N"),
    ("robot/finger_position", (0, 0, 0), 5e3, "/robot/finger_position: 5e+03 m"),
])
def test_an_implausible_value_is_named_by_the_reader(files, tmp_path, path, index, value, fragment):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(files["a"].read_bytes())
    with h5py.File(bad, "r+") as f:
        data = f[path][()]
        data[index] = value
        f[path][...] = data
    res = tacest("estimate", bad, "-o", tmp_path / "est.h5")
    assert res.returncode == 2
    line = one_error_line(res)
    assert str(bad) in line and fragment in line and "plausibility limit" in line


def test_an_implausible_sample_period_is_named(files, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(files["a"].read_bytes())
    with h5py.File(bad, "r+") as f:
        f.attrs["dt"] = 1e-9
        f["time"][...] = f["time"][()] * 1e-7
    res = tacest("eval", files["est"], "--truth", bad)
    assert res.returncode == 2 and "attrs dt" in one_error_line(res)


def test_bare_tacest_prints_the_help_and_succeeds():
    res = tacest()
    assert res.returncode == 0 and res.stderr == ""
    assert res.stdout == tacest("--help").stdout


def test_a_bug_has_its_own_status_and_the_debug_hint(files, monkeypatch, capsys):
    import tacest.evaluation.metrics as metrics
    from tacest.cli.main import main

    def broken(*args, **kwargs):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(metrics, "evaluate_files", broken)
    monkeypatch.delenv("TACEST_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exc:
        main(["eval", str(files["est"]), "--truth", str(files["a"])])
    assert exc.value.code == EXIT_BUG
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tacest: internal error: ZeroDivisionError")
    assert "TACEST_DEBUG=1" in err[0]
    monkeypatch.setenv("TACEST_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        main(["eval", str(files["est"]), "--truth", str(files["a"])])


def test_bad_input_stays_status_2(files, tmp_path):
    res = tacest("estimate", tmp_path / "missing.h5", "-o", tmp_path / "est.h5")
    assert res.returncode == EXIT_BAD_INPUT and "no such file" in one_error_line(res)
