"""``tacest record --source sim`` end to end: exit status, files, one-line errors."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from tacest.cli.main import cli
from tacest.io.plan import Plan, write_plan
from tacest.io.run import read_run
from tacest.sim.effects import effects_from_json

TACEST = str(Path(sys.executable).parent / "tacest")


def _tacest(*args):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120)


def test_record_sim_writes_a_valid_run(tmp_path):
    out = tmp_path / "run.h5"
    res = _tacest("record", "--source", "sim", "--object", "polygon:5", "--seed", "4", "--pokes", "2",
                  "--effect", "latency:samples=2", "--effect", "force_bias", "--observe-pose", "0.001", "-o", out)
    assert res.returncode == 0, res.stderr
    assert "poke 2/2" in res.stderr and f"wrote {out}" in res.stderr
    run = read_run(out)
    assert run.source == "sim" and run.dim == 2 and run.has_pose_obs
    assert len(run.truth.vertices) == 5 and run.actions.params.shape == (2, 6)
    assert [e.name for e in effects_from_json(run.truth.effects)] == ["latency", "force_bias"]


def test_cli_runner_no_truth_no_force_quiet(tmp_path):
    out = tmp_path / "hidden.h5"
    res = CliRunner().invoke(cli, ["record", "--pokes", "1", "--no-truth", "--no-force", "--quiet",
                                   "--effect", "restitution", "-o", str(out)])
    assert res.exit_code == 0, res.output
    run = read_run(out)
    assert run.truth is None and run.force is None and run.contact.any()


@pytest.mark.parametrize("args,msg", [
    (["--effect", "wobble"], "unknown effect 'wobble'; valid effects: none, restitution"),
    (["--effect", "latency:delay=2"], "has no parameter 'delay'; valid: samples"),
    (["--dim", "3", "--object", "box:0.1,0.1"], "a 3-D box takes three extents"),
    (["--object", "sphere"], "--object sphere"),
    (["--seed", "-1"], "--seed must be >= 0"),
    (["--toss", "--plan", "p.h5", "--dim", "3"], "p.h5"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, args, msg):
    out = tmp_path / "x.h5"
    res = _tacest("record", "--source", "sim", "--pokes", "1", *args, "-o", out)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert lines[-1].startswith("tacest: error: ") and msg in lines[-1]
    assert "Traceback" not in res.stderr
    assert not out.exists()


def test_plan_appends_through_the_cli(tmp_path):
    out = tmp_path / "run.h5"
    assert _tacest("record", "--pokes", "1", "--seed", "2", "-o", out).returncode == 0
    first = read_run(out)
    q = first.truth.pose[-1]
    plan = tmp_path / "plan.h5"
    write_plan(Plan(chosen=np.array([0, 0.5, q[0], q[1], 0.02, 0.04]), candidates=np.zeros((0, 6)),
                    scores=np.zeros(0), method="random", score="logdet"), plan)
    res = _tacest("record", "--plan", plan, "--seed", "2", "-o", out)
    assert res.returncode == 0, res.stderr
    run = read_run(out)
    assert run.n_samples > first.n_samples and len(run.actions.segments) == 2
    assert np.array_equal(run.truth.pose[:first.n_samples], first.truth.pose)


def test_toss_through_the_cli(tmp_path):
    out = tmp_path / "toss.h5"
    res = _tacest("record", "--toss", "--pokes", "1", "--seed", "3", "--observe-pose", "5e-4", "-o", out)
    assert res.returncode == 0, res.stderr
    assert "tossed" in res.stderr
    run = read_run(out)
    start = int(run.actions.segments[0, 0])
    assert start > 10, "the poke starts after the flight and landing"
    assert not run.contact[:start].any(), "the parked finger never touches the tossed object"
    assert run.contact[start:].any()
