"""Property-based fuzzing of the file readers through every command that reads them
(issue 27, item 7).

Valid run, estimate and plan files written by tacest's own writers are corrupted by
Hypothesis — an item or attribute dropped, a dataset reshaped, retyped or poisoned with
NaN, inf or an absurd value, an attribute replaced, a group swapped for a dataset, the
file truncated — and handed to a command that reads that kind of file.  The property:
the command either accepts the file or exits 2 with one line that names the file; never
a traceback, never the bug status 3, and a file that is certainly invalid (a required
item missing, NaN or inf where a value is required, a truncated file, another format) is
never accepted.

"Accepted" means the command got past reading and validating its inputs: the expensive
step after that (the solve, the planner's search, the diagnosis, the simulation) is
replaced by a stub that runs the command's own checks of what it was handed and then
stops (``Reached``).  ``tacest eval`` runs in full.

CI runs FUZZ_EXAMPLES cases (a few hundred, well under a minute); for a longer run set
TACEST_FUZZ_EXAMPLES, e.g. ``benchmarks/bench_fuzz.py`` (thousands).
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.reliability_files import make_run, poke_plan, truth_estimate

#: a numpy warning (overflow in a check) would be a second line on a user's stderr
pytestmark = [pytest.mark.filterwarnings("error::RuntimeWarning"),
              pytest.mark.filterwarnings("error::numpy.exceptions.ComplexWarning")]

#: cases per CI run (each reads one corrupted file through one command: ~10-50 ms);
#: CI's cases are the same every run (derandomized), a longer run draws new ones
FUZZ_EXAMPLES = int(os.environ.get("TACEST_FUZZ_EXAMPLES", "300"))
FUZZ_RANDOM = "TACEST_FUZZ_EXAMPLES" in os.environ


class Reached(BaseException):
    """Raised by the stubs: the command accepted its inputs (not an Exception, so the
    CLI's handlers let it through)."""


# ---------------------------------------------------------------------------------
# the valid files


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    run = make_run(d / "run.h5", seed=2, pokes=2, observe_pose=1e-3)
    est = truth_estimate([run], d / "est.h5")
    plan = poke_plan(d / "plan.h5", [run], est)
    return {"run": run, "estimate": est, "plan": plan}


@pytest.fixture(scope="module")
def stubs():
    """Replace the expensive step of each command by its input checks and ``Reached``."""
    import tacest.diagnosis.diagnose as diagnose_mod
    import tacest.dims as dims_mod
    import tacest.estimation.estimator as estimator_mod
    import tacest.planning.planner as planner_mod
    import tacest.sim.record as record_mod

    def estimate_runs(runs, shape_spec="box", config=None, method="implicit", **kwargs):
        dims_mod.dimension_of(runs)
        estimator_mod.check_runs(runs)
        raise Reached

    def plan_next(est, runs, settings=None):
        from tacest.information.expected import ModelState

        ModelState.from_estimate(est, runs)
        raise Reached

    def diagnose(runs, shape="box", config=None, options=None, estimate=None, **_):
        diagnose_mod.check_heldout_data(runs)
        if estimate is not None:
            diagnose_mod.check_estimate_matches(estimate, runs)
        raise Reached

    def record_sim(opts, plan_path=None, append_to=None):
        from tacest.io.run import read_run
        from tacest.sim.pokes import Poke

        plan = record_mod._plan_pokes(plan_path)
        fingers = 1
        if append_to is not None:
            fingers = record_mod.state_from_run(read_run(append_to)).n_fingers
        Poke.from_vector(plan.chosen, fingers, plan.names)
        raise Reached

    # the CLI takes estimate_runs from the dimension registry (tacest.dims), which takes
    # the 2-D recorder from tacest.sim.record when called
    saved = [(dims_mod, "estimate_runs"), (planner_mod, "plan_next"), (diagnose_mod, "diagnose"),
             (record_mod, "record_sim")]
    originals = [getattr(m, n) for m, n in saved]
    for (m, n), f in zip(saved, (estimate_runs, plan_next, diagnose, record_sim)):
        setattr(m, n, f)
    yield
    for (m, n), f in zip(saved, originals):
        setattr(m, n, f)


#: kind of file -> the commands that read it, as argv builders (bad: the corrupted
#: file; f: the valid files; out: a fresh folder for outputs)
COMMANDS = {
    "run": [
        lambda bad, f, out: ["estimate", bad, "-o", out / "est.h5"],
        lambda bad, f, out: ["eval", f["estimate"], "--truth", bad],
        lambda bad, f, out: ["plan", f["estimate"], bad, "-o", out / "plan.h5"],
        lambda bad, f, out: ["diagnose", bad, "--effects", "latency", "-o", out / "report"],
    ],
    "estimate": [
        lambda bad, f, out: ["plan", bad, f["run"], "-o", out / "plan.h5"],
        lambda bad, f, out: ["eval", bad, "--truth", f["run"]],
        lambda bad, f, out: ["diagnose", f["run"], "--estimate", bad, "--effects", "latency", "-o", out / "report"],
    ],
    "plan": [
        lambda bad, f, out: ["record", "--plan", bad, "-o", out / "new.h5"],
        lambda bad, f, out: ["record", "--plan", bad, "-o", out / "continued.h5"],
    ],
}

#: items every file of the kind needs (dropping one must be refused)
REQUIRED = {
    "run": ("/time", "/robot", "/robot/finger_position", "/robot/finger_radius", "/tactile/contact",
            "/tactile/normal", "/actions/segments", "/actions/params"),
    "estimate": ("/params", "/params/vertices", "/runs", "/runs/0", "/runs/0/pose", "/runs/0/velocity"),
    "plan": ("/chosen", "/chosen/params", "/candidates", "/candidates/params", "/candidates/score"),
}
REQUIRED_ATTRS = {
    "run": {"/": ("format", "version", "dim", "dt", "gravity")},
    "estimate": {"/": ("format", "version", "dim"), "/params": ("mass", "inertia", "friction_ground",
                                                               "friction_finger")},
    "plan": {"/": ("method", "score")},
}
#: datasets where NaN or inf is never a valid value
FINITE = {
    "run": ("/time", "/robot/finger_position", "/robot/finger_radius", "/tactile/force", "/tactile/contact",
            "/actions/params", "/actions/segments"),
    "estimate": ("/params/vertices", "/runs/0/pose", "/runs/0/velocity"),
    "plan": ("/chosen/params", "/candidates/params"),
}

#: values an attribute is replaced with
ATTR_VALUES = st.sampled_from([
    "text", "", "{", "[1, 2]", '{"name": 1}', b"\xff\xfe", 0, -1, 1, 2, 3, 1.5, 1e300, -1e300, float("nan"),
    float("inf"), True, np.arange(3.0), np.eye(3), np.array(["a", "b"], dtype=object), np.zeros(0),
])
POISON = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 1e30, 0.0, -1.0, 2.0, 0.5])


# ---------------------------------------------------------------------------------
# corruption


def _items(f):
    found = []
    f.visititems(lambda name, obj: found.append("/" + name))
    return sorted(found)


def _attr_slots(f):
    slots = [("/", k) for k in f.attrs]
    for name in _items(f):
        slots += [(name, k) for k in f[name].attrs]
    return slots


def _reshaped(a: np.ndarray, how: int) -> np.ndarray:
    flat = a.reshape(-1)
    return [flat, flat[None], a[..., None], a[:-1] if a.ndim and len(a) else a, np.zeros((0,) + a.shape[1:]),
            a.T if a.ndim > 1 else flat[None].T, flat[:1].reshape(()) if flat.size else np.float64(0)][how]


def _retyped(a: np.ndarray, how: int):
    return [np.full(a.shape, b"text", dtype="S4"), a.astype(np.int8) if a.dtype.kind == "f" and np.all(
        np.isfinite(a)) else a.astype(float), a.astype(bool), np.array(b"a string"),
        a.astype(np.complex128) if a.dtype.kind in "fiu" else np.zeros(3, np.complex128)][how]


def corrupt(path: Path, kind: str, data) -> dict:
    """Corrupt the HDF5 file at ``path`` in place with draws from ``data``; returns what
    was done: {"op", "path", "invalid" (certainly invalid: must be refused)}."""
    op = data.draw(st.sampled_from(["drop", "drop_attr", "reshape", "retype", "poison", "attr", "swap",
                                    "truncate"]), label="op")
    if op == "truncate":
        size = path.stat().st_size
        keep = data.draw(st.integers(0, size - 1), label="keep bytes")
        with open(path, "r+b") as fh:
            fh.truncate(keep)
        return {"op": op, "path": f"{keep} of {size} bytes", "invalid": True}
    with h5py.File(path, "r+") as f:
        items = _items(f)
        datasets = [n for n in items if isinstance(f[n], h5py.Dataset)]
        if op == "drop":
            name = data.draw(st.sampled_from(items), label="item")
            del f[name]
            return {"op": op, "path": name, "invalid": name in REQUIRED[kind]}
        if op in ("drop_attr", "attr"):
            slots = _attr_slots(f)
            if not slots:
                return {"op": "none", "path": "", "invalid": False}
            holder, key = data.draw(st.sampled_from(slots), label="attr")
            obj = f[holder]
            required = key in REQUIRED_ATTRS[kind].get(holder, ())
            if op == "drop_attr":
                del obj.attrs[key]
                return {"op": op, "path": f"{holder} attrs {key}", "invalid": required}
            value = data.draw(ATTR_VALUES, label="value")
            obj.attrs[key] = value
            invalid = (holder, key) == ("/", "format")  # no ATTR_VALUES entry is a format name
            return {"op": op, "path": f"{holder} attrs {key} = {value!r}", "invalid": invalid}
        if op == "swap":
            name = data.draw(st.sampled_from(items), label="item")
            del f[name]
            if name in datasets:
                f.create_group(name)
            else:
                f.create_dataset(name, data=np.zeros(3))
            return {"op": op, "path": name, "invalid": name in REQUIRED[kind]}
        name = data.draw(st.sampled_from(datasets), label="dataset")
        a = f[name][()]
        if op == "reshape":
            new = _reshaped(np.asarray(a), data.draw(st.integers(0, 6), label="how"))
        elif op == "retype":
            new = _retyped(np.asarray(a), data.draw(st.integers(0, 4), label="how"))
        else:  # poison one entry
            new = np.array(a, dtype=float, copy=True)
            if new.size == 0:
                return {"op": "none", "path": name, "invalid": False}
            flat_index = data.draw(st.integers(0, new.size - 1), label="index")
            value = data.draw(POISON, label="value")
            new.reshape(-1)[flat_index] = value
            invalid = not np.isfinite(value) and name in FINITE[kind]
            del f[name]
            f.create_dataset(name, data=new)
            return {"op": op, "path": f"{name}[{flat_index}] = {value}", "invalid": invalid}
        del f[name]
        f.create_dataset(name, data=new)
        return {"op": op, "path": name, "invalid": False}


# ---------------------------------------------------------------------------------
# the property


def run_command(argv) -> tuple:
    """(outcome, stderr) of ``tacest argv`` in this process: outcome is an exit status
    or "reached" (the stub stopped it after its input checks)."""
    from tacest.cli.main import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main([str(a) for a in argv])
        except SystemExit as exc:
            return exc.code, err.getvalue()
        except Reached:
            return "reached", err.getvalue()
    return 0, err.getvalue()


def check_case(base_files, kind, data):
    work = Path(tempfile.mkdtemp(prefix="tacest-fuzz-"))
    try:
        files = {k: work / p.name for k, p in base_files.items()}
        for k, p in base_files.items():
            shutil.copyfile(p, files[k])
        bad = work / f"bad_{kind}.h5"
        shutil.copyfile(base_files[kind], bad)
        shutil.copyfile(base_files["run"], work / "continued.h5")
        done = corrupt(bad, kind, data)
        command = data.draw(st.sampled_from(COMMANDS[kind]), label="command")
        argv = command(bad, files, work)
        outcome, err = run_command(argv)
        where = f"{done} -> tacest {' '.join(map(str, argv))}: {outcome}\n{err}"
        assert "Traceback" not in err, where
        assert outcome in (0, 2, "reached"), where  # never the bug status 3
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("note:")]
        if outcome == 2:
            assert len(lines) == 1 and lines[0].startswith("tacest: error:"), where
            assert bad.name in lines[0], where
        if done["invalid"]:
            assert outcome == 2, where
    finally:
        shutil.rmtree(work, ignore_errors=True)


FUZZ_SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None, database=None, derandomize=not FUZZ_RANDOM,
                         suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                HealthCheck.function_scoped_fixture])


@FUZZ_SETTINGS
@given(kind=st.sampled_from(["run", "estimate", "plan"]), data=st.data())
def test_every_command_accepts_or_names_a_corrupted_file(base, stubs, kind, data):
    check_case(base, kind, data)


def test_the_stubs_are_reached_with_the_valid_files(base, stubs, tmp_path):
    """The fuzzing's "accepted" outcome exists: every command accepts the valid files."""
    shutil.copyfile(base["run"], tmp_path / "continued.h5")
    for kind, commands in COMMANDS.items():
        for command in commands:
            argv = command(base[kind], base, tmp_path)
            if argv[-1] == tmp_path / "continued.h5":
                shutil.copyfile(base["run"], tmp_path / "continued.h5")  # the run the plan was made from
            outcome, err = run_command(argv)
            assert outcome in ("reached", 0), (argv, outcome, err)
