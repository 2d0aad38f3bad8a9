"""The ``tacest`` entry point as a user meets it: help, version, usage errors.

Runs the installed console script (next to this Python), so the entry point in
setup.cfg and the lazy command table in cli/main.py are tested as shipped.
"""

import subprocess
import sys
from pathlib import Path

import pytest

from tacest import __version__
from tacest.cli.main import COMMANDS

TACEST = str(Path(sys.executable).parent / "tacest")


def _tacest(*args, cwd=None):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120, cwd=cwd)


def _one_error_line(res):
    """The single stderr line of a failed command (asserts there is exactly one)."""
    assert "Traceback" not in res.stderr, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("tacest: error:"), lines[0]
    return lines[0]


def test_help_lists_every_command():
    res = _tacest("--help")
    assert res.returncode == 0, res.stderr
    assert "Usage: tacest" in res.stdout
    for name in ("record", "estimate", "plan", "explore", "eval", "diagnose", "demo"):
        assert name in COMMANDS
        assert f"\n  {name} " in res.stdout, f"{name} missing from tacest --help"
    assert res.stderr == ""


def test_short_help_option():
    res = _tacest("-h")
    assert res.returncode == 0 and "Commands:" in res.stdout


def test_no_arguments_shows_usage():
    res = _tacest()
    # a bare `tacest` prints the help on stdout and succeeds (docs/index.md, "Exit status")
    assert res.returncode == 0 and "Usage: tacest" in res.stdout
    assert res.stderr == ""


def test_version():
    res = _tacest("--version")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == f"tacest, version {__version__}"


def test_python_m_tacest_is_the_same_cli():
    res = subprocess.run([sys.executable, "-m", "tacest", "--version"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and __version__ in res.stdout


@pytest.mark.parametrize("args,fragment", [
    (["--bogus"], "No such option '--bogus'"),
    (["frobnicate"], "No such command 'frobnicate'"),
    (["record", "--bogus", "-o", "x.h5"], "No such option '--bogus'"),
    (["estimate", "--bogus", "x.h5"], "No such option '--bogus'"),
    (["record", "--source", "sim", "--pokes", "many", "-o", "x.h5"], "--pokes"),
    (["estimate", "run.h5"], "Missing option '-o'"),
])
def test_usage_errors_exit_2_with_one_line(tmp_path, args, fragment):
    res = _tacest(*args, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert fragment in line, line
    assert res.stdout == ""
    assert not (tmp_path / "x.h5").exists()


def test_estimate_missing_file_names_it(tmp_path):
    res = _tacest("estimate", "missing.h5", "-o", "x.h5", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert "missing.h5" in line and "no such file" in line
    assert not (tmp_path / "x.h5").exists()


def test_estimate_not_hdf5_names_it(tmp_path):
    (tmp_path / "notes.h5").write_text("not an HDF5 file\n")
    res = _tacest("estimate", "notes.h5", "-o", "x.h5", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert "notes.h5" in line and "HDF5" in line


def test_eval_missing_file_names_it(tmp_path):
    res = _tacest("eval", "nope.h5", "--truth", "truth.h5", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "nope.h5" in _one_error_line(res)


@pytest.mark.parametrize("name", [n for n, (mod, _, _) in COMMANDS.items()])
def test_every_listed_command_has_help(name):
    # a command not available in this version still answers --help (exit 0)
    res = _tacest(name, "--help")
    assert res.returncode == 0, res.stderr
    assert f"Usage: tacest {name}" in res.stdout


# ---------------------------------------------------------------------------------
# tacest demo: the plumbing, with the estimator replaced (a real solve takes ~30 s and
# belongs to the estimation tests); the record, eval and plot stages run for real


def _run_demo(tmp_path, capsys, args):
    from tacest.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(["demo", "-o", str(tmp_path / "out"), "--quiet", *args])
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def test_demo_writes_every_file_and_an_honest_summary(tmp_path, capsys, monkeypatch):
    import json

    import numpy as np

    import tacest.dims as dims
    from tacest.io.estimate import Estimate, RunEstimate

    def truth_as_estimate(runs, shape, config=None, method="implicit"):
        (run,) = runs
        tr = run.truth
        return Estimate(dim=2, shape=shape, vertices=tr.vertices, runs=[RunEstimate(
            pose=tr.pose, velocity=np.zeros_like(tr.pose), source_file=run.filename)],
            params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                    "friction_finger": 0.5},
            identifiable={"mass": True, "inertia": True, "friction_ground": True, "friction_finger": False},
            solver_status="Solve_Succeeded", success=True, iterations=7)

    monkeypatch.setattr(dims, "estimate_runs", truth_as_estimate)
    code, out, err = _run_demo(tmp_path, capsys, ["--seed", "1"])
    assert code == 0, err
    assert err == ""  # --quiet
    d = tmp_path / "out"
    for name in ("run.h5", "estimate.h5", "eval.json", "eval.png"):
        assert (d / name).is_file(), name
    report = json.loads((d / "eval.json").read_text())
    assert report["chamfer"] < 1e-3 and report["solver_status"] == "Solve_Succeeded"
    assert "seed 1" in out and "6 pokes" in out and "Solve_Succeeded, 7 iterations" in out
    assert "Chamfer, placed shapes" in out and " mm" in out
    assert "truth" in out and "poorly determined" in out  # friction_finger flagged as weakly determined
    for stage in ("plan", "diagnose"):
        line = next(ln for ln in out.splitlines() if ln.startswith(stage + ":"))
        assert "not available in this version yet" in line or "available as" in line
    assert "wall time" in out


def test_demo_reports_a_failed_solve_and_exits_2(tmp_path, capsys, monkeypatch):
    import tacest.dims as dims
    from tacest.errors import SolveFailedError

    def fails(*args, **kwargs):
        raise SolveFailedError("IPOPT failed in stage 'homotopy 2/2': Maximum_Iterations_Exceeded")

    d = tmp_path / "out"
    d.mkdir()
    (d / "estimate.h5").write_text("from an earlier demo")
    monkeypatch.setattr(dims, "estimate_runs", fails)
    code, out, err = _run_demo(tmp_path, capsys, [])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "solve failed" in lines[0] and "Maximum_Iterations_Exceeded" in lines[0]
    assert out == ""  # no summary, nothing that looks like a result
    assert (d / "run.h5").is_file()
    assert not (d / "estimate.h5").exists() and not (d / "eval.json").exists()


def test_demo_output_that_is_a_file_is_an_error(tmp_path):
    (tmp_path / "taken").write_text("")
    res = _tacest("demo", "-o", "taken", cwd=tmp_path)
    assert res.returncode == 2
    assert "taken" in _one_error_line(res)


def test_an_estimate_that_used_up_its_budget_is_warned_in_one_line():
    """An estimate kept although its final stage used up IPOPT's iteration budget (it
    beat every converged start's objective: solver.solve_from_starts) gets one warning
    line naming the status; a converged, consistent one gets none."""
    import io
    from types import SimpleNamespace

    from tacest.cli.logs import setup_logging, warn_fit_quality

    stream = io.StringIO()
    setup_logging(quiet=True, stream=stream)
    warn_fit_quality(SimpleNamespace(success=True, solver_status="Solve_Succeeded", iterations=30, consistent=True,
                                     local_misfit=False, fit_quality={}))
    assert stream.getvalue() == ""
    warn_fit_quality(SimpleNamespace(success=False, solver_status="Maximum_Iterations_Exceeded", iterations=861,
                                     consistent=True, local_misfit=False, fit_quality={}))
    lines = stream.getvalue().strip().splitlines()
    assert len(lines) == 1 and "Maximum_Iterations_Exceeded" in lines[0] and "861 iterations" in lines[0]
    setup_logging(quiet=False)
