"""The executor (tacest.parallel, issue 29): where tasks run (--workers, --scheduler and
the environment), the in-process executor (order, dependencies, errors, progress), a
local Dask cluster (same results as in process, every worker used, a worker that dies
is replaced and its task rerun, an error ends the graph), the progress bar, kernels
compiled once under a lock, Ctrl-C of a distributed diagnosis (exit 130, no output), and
a real cluster of separate processes (``dask scheduler``, two ``dask worker``) running a
diagnosis and a batch through --scheduler with the in-process results (slow)."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tacest.errors import SolveFailedError, TacestError
from tacest.parallel import (ENV_SCHEDULER, ENV_WORKERS, PROGRESS_ATTR, Executor, ParallelSettings,
                             machine_workers, parse_workers)
from tests.reliability_files import TACEST, make_run

DASK = str(Path(sys.executable).parent / "dask")


# ------------------------------------------------------------------------------------
# where tasks run


def test_settings_default_to_this_process_and_options_win_over_the_environment():
    assert ParallelSettings.resolve(environ={}).in_process
    assert ParallelSettings.resolve(workers="3", environ={}) == ParallelSettings(workers=3)
    assert ParallelSettings.resolve(workers="auto", environ={}).workers == machine_workers()
    env = {ENV_SCHEDULER: "tcp://10.1.2.3:8786", ENV_WORKERS: "4"}
    assert ParallelSettings.resolve(environ=env).scheduler == "tcp://10.1.2.3:8786"
    assert ParallelSettings.resolve(environ={ENV_WORKERS: "4"}).workers == 4
    assert ParallelSettings.resolve(workers="1", environ=env).in_process  # the option wins
    assert ParallelSettings.resolve(scheduler="tcp://h:1", environ=env).scheduler == "tcp://h:1"
    with pytest.raises(TacestError, match="exclude each other"):
        ParallelSettings.resolve(workers="2", scheduler="tcp://h:1", environ={})
    for bad in ("0", "-2", "two", "1.5", ""):
        with pytest.raises(TacestError, match="--workers"):
            parse_workers(bad)


# ------------------------------------------------------------------------------------
# tasks (module-level functions: a worker imports them by name)


def _add(a, b):
    return a + b


def _total(values, scale=1):
    return scale * sum(values)


def _fail(message):
    raise SolveFailedError(message)


def _slow_pid(x, seconds=0.3):
    time.sleep(seconds)
    return x * x, os.getpid()


def _die_once(marker):
    """Kills its worker process the first time (a crash, the OOM killer), returns
    "rerun" when run again elsewhere."""
    marker = Path(marker)
    if not marker.exists():
        marker.write_text("died")
        os._exit(1)
    return "rerun"


def _graph(ex):
    """A small graph with scattered data and dependencies; its results."""
    data = ex.scatter(list(range(10)))
    a = ex.submit(_total, data, name="a")
    b = ex.submit(_total, data, scale=2, name="b")
    c = ex.submit(_add, a, b, name="c")
    d = [ex.submit(_slow_pid, i, name="sq") for i in range(6)]
    return ex.gather([a, b, c]) + [r[0] for r in ex.gather(d)], {r[1] for r in ex.gather(d)}


def test_in_process_runs_in_order_of_submission_and_reports_progress(caplog):
    ran = []

    def task(i):
        ran.append(i)
        return i

    ex = Executor()
    ex.plan(3, what="work")
    handles = [ex.submit(task, i) for i in range(3)]
    assert ran == []  # a task runs when its result is first needed
    with caplog.at_level(logging.INFO, logger="tacest.parallel"):
        assert ex.gather(handles[1:2]) == [1]
        assert ran == [0, 1]
        assert ex.gather(handles) == [0, 1, 2]
    assert ran == [0, 1, 2]  # each once
    progress = [getattr(r, PROGRESS_ATTR) for r in caplog.records if hasattr(r, PROGRESS_ATTR)]
    assert progress[-1]["done"] == progress[-1]["total"] == 3 and progress[-1]["what"] == "work"
    assert ex.tasks_per_worker() == {"in-process": 3}
    results, pids = _graph(Executor())
    assert results == [45, 90, 135, 0, 1, 4, 9, 16, 25] and pids == {os.getpid()}


def test_in_process_error_ends_the_run_with_its_exception():
    ran = []
    ex = Executor()
    first = ex.submit(_fail, "Restoration_Failed")
    later = ex.submit(ran.append, 1)
    with pytest.raises(SolveFailedError, match="Restoration_Failed"):
        ex.gather([first, later])
    assert ran == []


@pytest.fixture(scope="module")
def cluster():
    with Executor(ParallelSettings(workers=2)) as ex:
        yield ex


def test_a_local_cluster_gives_the_in_process_results_on_every_worker(cluster):
    results, pids = _graph(cluster)
    assert results == _graph(Executor())[0]
    assert len(pids) == 2 and os.getpid() not in pids  # both workers, not this process
    assert len(cluster.workers()) == 2


def test_a_task_error_reaches_the_caller_and_the_cluster_goes_on(cluster):
    h = cluster.submit(_fail, "Maximum_Iterations_Exceeded")
    with pytest.raises(SolveFailedError, match="Maximum_Iterations_Exceeded"):
        cluster.gather([h])
    assert cluster.result(cluster.submit(_add, 1, 2)) == 3


def test_a_worker_that_dies_is_replaced_and_its_task_rerun(cluster, tmp_path):
    assert cluster.result(cluster.submit(_die_once, str(tmp_path / "died"))) == "rerun"
    assert (tmp_path / "died").exists()
    deadline = time.monotonic() + 60
    while len(cluster.workers()) < 2 and time.monotonic() < deadline:  # the nanny restarts it
        time.sleep(0.2)
    assert len(cluster.workers()) == 2


# ------------------------------------------------------------------------------------
# the progress bar of the command line


class _Tty(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("tty", [True, False])
def test_progress_is_one_bar_on_a_terminal_and_lines_elsewhere(tty):
    from tacest.cli.logs import setup_logging

    stream = _Tty() if tty else io.StringIO()
    logger = setup_logging(stream=stream)
    try:
        ex = Executor()
        ex.plan(2, what="batch")
        hs = [ex.submit(time.sleep, 1.1) for _ in range(2)]
        ex.gather(hs)
        logging.getLogger("tacest.test").info("after")
    finally:
        setup_logging(stream=sys.stderr)
    text = stream.getvalue()
    if tty:
        assert text.startswith("\rbatch [") and "1/2" in text and "\rbatch [" + "#" * 24 + "] 2/2" in text
        assert text.endswith("] 2/2 100%  0:02 elapsed, ~0:00 left\nafter\n"), repr(text)
    else:
        lines = text.splitlines()
        assert lines[0].startswith("batch: 1/2 done (50%)") and lines[1].startswith("batch: 2/2 done (100%)")
        assert lines[-1] == "after" and "\r" not in text
    assert logger.name == "tacest"


# ------------------------------------------------------------------------------------
# compiled kernels: once per machine, whoever asks at the same time


def test_kernels_are_compiled_once_when_threads_ask_at_once(tmp_path, monkeypatch):
    import casadi as ca

    from tacest.estimation import kernels

    if kernels._compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("TACEST_CACHE", str(tmp_path))
    monkeypatch.delenv("TACEST_NO_COMPILE", raising=False)
    calls = []
    real = kernels.subprocess.run

    def counting(*args, **kwargs):
        calls.append(args)
        time.sleep(0.5)  # a slow compiler: the others arrive while it works
        return real(*args, **kwargs)

    monkeypatch.setattr(kernels.subprocess, "run", counting)
    x = ca.SX.sym("x", 3)
    f = ca.Function("race_f", [x], [ca.sin(x) * ca.dot(x, x)])
    out, errors = [], []

    def ask():
        try:
            out.append(kernels.compile_functions([f], "race"))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(out) == 4
    assert len(calls) == 1  # compiled once; the others waited and loaded it
    files = sorted(p.name for p in (tmp_path / "kernels").iterdir())
    assert [n for n in files if n.endswith(".so")] and not [n for n in files if n.endswith(".part")], files
    for funs in out:
        assert float(funs["race_f"]([1.0, 2.0, 3.0])[0]) == pytest.approx(float(f([1.0, 2.0, 3.0])[0]))


# ------------------------------------------------------------------------------------
# Ctrl-C of a distributed run


def test_ctrl_c_cancels_a_distributed_diagnosis_and_writes_nothing(tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C sends it (the local
    workers get it too): exit 130, one line, no report, no worker left behind."""
    run = make_run(tmp_path / "a.h5", seed=1, pokes=3)
    report = tmp_path / "report"
    p = subprocess.Popen([TACEST, "diagnose", str(run), "--effects", "latency", "--workers", "2", "-o", str(report)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    seen = []
    for line in p.stderr:
        seen.append(line.rstrip("\n"))
        if line.startswith("plain model: fitting"):
            break
    time.sleep(2.0)
    assert p.poll() is None, seen
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=120)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert p.returncode == 130, seen + lines
    assert lines and lines[-1] == "tacest: interrupted", lines
    assert not any("Traceback" in ln or "Error" in ln for ln in lines), lines
    assert not report.exists() and sorted(x.name for x in tmp_path.iterdir()) == ["a.h5"]
    deadline, left = time.monotonic() + 20, ["?"]
    while left and time.monotonic() < deadline:  # the workers (and the helper processes) end with it
        time.sleep(0.5)
        left = subprocess.run(["pgrep", "-g", str(p.pid)], capture_output=True, text=True).stdout.split()
    assert not left, left


# ------------------------------------------------------------------------------------
# a cluster of separate processes on this machine (slow)


def _start(args, log_path):
    return subprocess.Popen(args, stdout=open(log_path, "w"), stderr=subprocess.STDOUT, start_new_session=True)


@pytest.fixture
def dask_cluster(tmp_path):
    """``dask scheduler`` and two ``dask worker`` (one thread each) on 127.0.0.1, as
    separate processes; yields the scheduler's address."""
    sched_file = tmp_path / "scheduler.json"
    procs = [_start([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], tmp_path / "scheduler.log")]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        for i in range(2):
            procs.append(_start([DASK, "worker", address, "--nthreads", "1", "--nworkers", "1", "--name", f"w{i}",
                                 "--no-dashboard", "--host", "127.0.0.1"], tmp_path / f"worker{i}.log"))
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def _run(*args, env=None):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=900,
                          env={**os.environ, **(env or {})})


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in ("wall_time", "command_line")}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


@pytest.mark.slow
def test_a_cluster_of_separate_processes_gives_the_in_process_results(dask_cluster, tmp_path):
    run = make_run(tmp_path / "diag.h5", seed=3, pokes=2, effects=["latency:samples=2"])
    diag = ["diagnose", run, "--effects", "latency", "--fit-iterations", "30", "--json"]
    remote = _run(*diag, "-o", tmp_path / "remote", "--scheduler", dask_cluster)
    assert remote.returncode == 0, remote.stderr[-2000:]
    used = [ln for ln in remote.stderr.splitlines() if ln.startswith("dask: ") and "tasks ran on" in ln]
    assert used and "ran on 2 worker(s)" in used[0], remote.stderr[-2000:]
    local = _run(*diag, "-o", tmp_path / "local", env={ENV_SCHEDULER: "", ENV_WORKERS: ""})
    assert local.returncode == 0, local.stderr[-2000:]
    a, b = json.loads(remote.stdout), json.loads(local.stdout)
    assert a["verdict"] == b["verdict"] == "latency"
    assert _strip(a) == _strip(b)  # every figure, to the last bit
    # a batch of two objects through the environment's scheduler, against this process
    for name, seed in (("one", 4), ("two", 5)):
        make_run(tmp_path / f"{name}.h5", seed=seed, pokes=2)
    (tmp_path / "objects.csv").write_text("object,run\none,one.h5\ntwo,two.h5\n")
    remote = _run("estimate", "--batch", tmp_path / "objects.csv", "-o", tmp_path / "b_remote",
                  env={ENV_SCHEDULER: dask_cluster})
    assert remote.returncode == 0, remote.stderr[-2000:]
    assert any("ran on 2 worker(s)" in ln for ln in remote.stderr.splitlines()), remote.stderr[-2000:]
    local = _run("estimate", "--batch", tmp_path / "objects.csv", "-o", tmp_path / "b_local", "--workers", "1")
    assert local.returncode == 0, local.stderr[-2000:]
    ra = json.loads((tmp_path / "b_remote" / "summary.json").read_text())["objects"]
    rb = json.loads((tmp_path / "b_local" / "summary.json").read_text())["objects"]
    assert [r["status"] for r in ra] == ["ok", "ok"]
    assert _strip(ra) == _strip(rb)
    from tacest.io.estimate import read_estimate

    for name in ("one", "two"):
        ea, eb = (read_estimate(tmp_path / d / f"{name}.h5") for d in ("b_remote", "b_local"))
        assert ea.params == eb.params and ea.runs[0].source_sha256 == eb.runs[0].source_sha256


def test_one_blas_thread_per_process_unless_the_user_chose():
    """import tacest sets OPENBLAS_NUM_THREADS=1 when the environment does not set it
    (docs/parallel.md, "Threads"), and leaves a user's choice alone."""
    import os
    import subprocess
    import sys

    code = "import os, tacest; print(os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "2"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2"


# ---------------------------------------------------------------------------------------
# compared starts solved in forked processes (solver.solve_from_starts, solver.start_workers)

def _fake_start_solve(start, abandon_above=float("inf")):
    """A stand-in for an estimator's per-start solve: start = (objective, physics), or
    None for a failed solve; returns what solve_from_starts takes, with the solving
    process's pid in ``found``."""
    import numpy as np

    from tacest.estimation.solver import SolveOutcome, StageInfo

    if start is None:
        raise SolveFailedError("IPOPT failed in stage 'homotopy 1/1': Restoration_Failed")
    obj, phys = start
    time.sleep(0.2)
    stage = StageInfo(name="homotopy 2/2", status="Solve_Succeeded", iterations=5, wall_time=0.2, objective=obj)
    out = SolveOutcome(z=np.full(3, obj), lam_g=np.zeros(0), lam_x=None, status="Solve_Succeeded", success=True,
                       iterations=5, wall_time=0.2, objective=obj, stages=[stage])
    return out, phys, ("saved", obj), None, {"pid": os.getpid()}


@pytest.fixture
def single_threaded(monkeypatch):
    """fork_processes as in a command's process (one thread): the clusters of earlier
    tests leave threads in this one, where it would not fork at all."""
    monkeypatch.setattr("tacest.parallel.threading.active_count", lambda: 1)


def test_a_worker_that_dies_is_one_clear_error_not_a_hang():
    from tacest.parallel import fork_map

    def job(k):
        if k == 1:
            os._exit(3)  # as the out-of-memory killer or a crash in a native solver would end it
        time.sleep(0.1)
        return k

    t0 = time.monotonic()
    with pytest.raises(TacestError, match="ended without a result"):
        fork_map(job, 3, 2)
    assert time.monotonic() - t0 < 30
    assert fork_map(lambda k: k + 1, 3, 2) == [1, 2, 3]  # and the next one works


def test_no_fork_beside_other_threads_off_linux_or_with_an_openmp_solver(monkeypatch):
    from tacest.estimation.config import EstimatorConfig, start_workers
    from tacest.parallel import fork_processes

    monkeypatch.setattr("tacest.parallel.machine_workers", lambda: 2)
    n_threads = threading.active_count()
    monkeypatch.setattr("tacest.parallel.threading.active_count", lambda: 1)
    assert fork_processes(0, 3) == 2
    monkeypatch.undo()
    monkeypatch.setattr("tacest.parallel.machine_workers", lambda: 2)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert threading.active_count() > n_threads >= 1 and fork_processes(0, 3) == 1
    finally:
        stop.set()
        other.join()
    monkeypatch.setattr("tacest.parallel.threading.active_count", lambda: 1)
    monkeypatch.setattr(sys, "platform", "darwin")
    assert fork_processes(0, 3) == 1
    cfg = EstimatorConfig()
    assert start_workers(cfg.solver) == 0
    assert start_workers(cfg.updated({"solver": {"linear_solver": "spral"}}).solver) == 1


def test_start_workers_does_not_change_the_solver_cache_key():
    from tacest.estimation.config import EstimatorConfig, solver_structure_key

    cfg = EstimatorConfig()
    key = solver_structure_key(cfg.solver)
    assert solver_structure_key(cfg.updated({"solver": {"start_workers": 1}}).solver) == key
    assert solver_structure_key(cfg.updated({"solver": {"max_iter": 401}}).solver) != key


def test_compared_starts_in_processes_give_the_same_fits_and_attempts(single_threaded):
    """The compared starts solved by 2 forked processes: the kept fit, its saved state
    and the attempts (failed start included) are those of the solves one after another,
    the compared solves ran outside this process, and the restart after them in it."""
    from tacest.estimation.solver import solve_from_starts

    starts = [({"start": f"s{k}"}, s) for k, s in enumerate([(50.0, 0.5), None, (40.0, 0.5), (30.0, 0.01)])]
    runs = {}
    for workers in (1, 2):
        attempts = []
        out, saved = solve_from_starts(starts, _fake_start_solve, 0.1, attempts, min_solves=3, workers=workers)
        runs[workers] = (out.objective, saved, [{k: v for k, v in a.items() if k != "pid"} for a in attempts],
                         [a.get("pid") for a in attempts])
    assert runs[1][:3] == runs[2][:3]
    assert runs[1][0] == 30.0 and [a["status"] for a in runs[1][2]] == ["Solve_Succeeded", "failed"] + [
        "Solve_Succeeded"] * 2
    pids = runs[2][3]
    assert pids[0] != os.getpid() and pids[2] != os.getpid() and pids[3] == os.getpid()


def test_restarts_in_processes_give_the_fits_and_attempts_of_one_after_another(single_threaded):
    """The restarts solved two at a time: a batch's fits are taken in order, those after
    the one that ends the search are discarded (the kept fit is the one-after-another
    search's, 40 not the discarded 30), and the attempts are the same; the batches ran
    outside this process."""
    from tacest.estimation.solver import solve_from_starts

    for fits, kept, n_attempts in (([(50.0, 0.5), (40.0, 0.01), (30.0, 0.01)], 40.0, 2),
                                   ([(50.0, 0.5), None, (45.0, 0.5), (40.0, 0.01), (30.0, 0.01)], 40.0, 4)):
        starts = [({"start": f"s{k}"}, s) for k, s in enumerate(fits)]
        runs = {}
        for workers in (1, 2):
            attempts = []
            out, saved = solve_from_starts(starts, _fake_start_solve, 0.1, attempts, min_solves=1, workers=workers)
            runs[workers] = (out.objective, saved, [{k: v for k, v in a.items() if k != "pid"} for a in attempts],
                             [a.get("pid") for a in attempts])
        assert runs[1][:3] == runs[2][:3]
        assert runs[1][0] == kept and len(runs[1][2]) == n_attempts
        assert all(pid != os.getpid() for pid in runs[2][3][1:] if pid is not None)


def _slow_start_solve(start, abandon_above=float("inf")):
    """A stand-in whose start (objective, physics, seconds) "iterates" 100 times over
    its seconds at that objective and stops, as IPOPT's callback does, as soon as
    solver.hopeless says so beside the best fit so far (read at every iteration)."""
    from tacest.estimation.solver import StartAbandoned, best_value, hopeless

    obj, phys, seconds = start
    for it in range(100):
        if hopeless(it, obj, best_value(abandon_above)):
            raise StartAbandoned(f"abandoned after {it} iterations")
        time.sleep(seconds / 100)
    return _fake_start_solve((obj, phys))


def test_a_start_solved_beside_another_is_stopped_as_soon_as_that_ones_fit_ends(single_threaded):
    """Two compared starts in two processes: the fast good one (50, 0.3 s) ends first and
    its objective reaches the slow hopeless one (800, 4 s) through shared memory, which
    stops after 20 iterations instead of running its 4 s; the kept fit is the same as
    with solver.abandon_hopeless off, one after another."""
    from tacest.estimation.solver import solve_from_starts

    starts = [({"start": "fast"}, (50.0, 0.01, 0.3)), ({"start": "slow"}, (800.0, 0.01, 4.0))]
    t0 = time.perf_counter()
    attempts = []
    out, saved = solve_from_starts(starts, _slow_start_solve, 0.1, attempts, min_solves=2, workers=2, abandon=True)
    wall = time.perf_counter() - t0
    assert out.objective == 50.0 and saved == ("saved", 50.0)
    assert [a["status"] for a in attempts] == ["Solve_Succeeded", "abandoned"]
    assert wall < 3.0  # 20 iterations of 40 ms after the fast one's 0.3 s, with fork overhead, far below 4 s
    off = []
    out_off, _ = solve_from_starts(starts[:1] + [({"start": "slow"}, (800.0, 0.01, 0.2))], _slow_start_solve, 0.1,
                                   off, min_solves=2, workers=1, abandon=False)
    assert out_off.objective == out.objective and [a["status"] for a in off] == ["Solve_Succeeded"] * 2


def test_fork_processes_follow_the_setting_and_never_fork_from_a_daemon(monkeypatch, single_threaded):
    import multiprocessing as mp

    from tacest.estimation.config import EstimatorConfig
    from tacest.parallel import fork_processes

    monkeypatch.setattr("tacest.parallel.machine_workers", lambda: 2)
    assert fork_processes(0, 3) == 2 and fork_processes(0, 1) == 1 and fork_processes(1, 3) == 1
    assert fork_processes(4, 3) == 3
    monkeypatch.setattr(mp.current_process(), "daemon", True, raising=False)
    assert fork_processes(0, 3) == 1
    assert EstimatorConfig().solver.start_workers == 0
    with pytest.raises(TacestError, match="start_workers"):
        EstimatorConfig().updated({"solver": {"start_workers": -1}})


def test_an_error_in_a_forked_start_solve_reaches_the_caller():
    from tacest.parallel import fork_map

    def job(k):
        if k == 1:
            raise ValueError("not a solve failure")
        if k == 0:
            time.sleep(20)  # the error of job 1 arrives first and is raised at once
        return k

    t0 = time.monotonic()
    with pytest.raises(ValueError, match="not a solve failure"):
        fork_map(job, 3, 2)
    assert time.monotonic() - t0 < 10
    assert fork_map(lambda k: k * k, 3, 2) == [0, 1, 4]


def test_map_in_processes_is_the_sequential_map_and_raises_a_jobs_failure(single_threaded):
    from tacest.estimation.solver import map_in_processes

    def job(k):
        return os.getpid(), k ** 2

    forked, in_process = map_in_processes(job, 3, 2), map_in_processes(job, 3, 1)
    assert [v for _, v in forked] == [v for _, v in in_process] == [0, 1, 4]
    assert all(pid != os.getpid() for pid, _ in forked) and all(pid == os.getpid() for pid, _ in in_process)

    def failing(k):
        if k == 2:
            raise SolveFailedError("no fit")
        return k

    for workers in (1, 2):
        with pytest.raises(SolveFailedError, match="no fit"):
            map_in_processes(failing, 3, workers)


def test_a_2d_estimate_is_the_same_with_its_starts_in_processes(tmp_path, single_threaded, monkeypatch):
    """A real estimate (2 pokes, the sampler's 2 starts compared): the same objective,
    shape, parameters and attempts with start_workers 2 as with 1, bit for bit (the
    forked solves are the same computations), and the forked path was taken."""
    import numpy as np

    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.estimator import estimate_2d
    from tacest.io.run import read_run

    monkeypatch.setattr("tacest.parallel.machine_workers", lambda: 2)
    run = read_run(make_run(tmp_path / "r.h5", seed=3, pokes=2))
    got = {}
    for workers in (1, 2):
        cfg = EstimatorConfig().updated({"solver": {"start_workers": workers}})
        with _capture("tacest.estimation.solver") as log_text:
            e = estimate_2d([run], "box", config=cfg)
        forked = "compared starts in 2 processes" in log_text.getvalue()
        assert forked == (workers == 2)
        got[workers] = (e.objective, e.vertices, e.params["mass"], e.params["friction_ground"],
                        json.loads(e.extra_attrs["starts"]))
    assert got[1][0] == got[2][0] and got[1][4] == got[2][4]
    np.testing.assert_array_equal(got[1][1], got[2][1])
    assert got[1][2:4] == got[2][2:4]


class _capture:
    """Capture a logger's INFO records as text (context manager yielding a StringIO)."""

    def __init__(self, name):
        self.logger, self.text = logging.getLogger(name), io.StringIO()
        self.handler = logging.StreamHandler(self.text)

    def __enter__(self):
        self.level = self.logger.level
        self.logger.setLevel(logging.INFO)
        self.logger.addHandler(self.handler)
        return self.text

    def __exit__(self, *exc):
        self.logger.removeHandler(self.handler)
        self.logger.setLevel(self.level)
