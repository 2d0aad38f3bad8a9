"""One executor for tacest's independent work: in this process, on a local Dask cluster,
or on any Dask cluster by address (docs/parallel.md).

Much of tacest's work is independent fits: a diagnosis fits the plain model and every
candidate effect on every fold, a batch estimates many objects.  Every such part submits
its tasks to an :class:`Executor` and gathers their results; the executor decides where
they run:

- ``workers=1`` (the default): in this process, each task when its result is first
  needed or when the executor waits, in the order of submission, exactly as a loop
  would run them (no Dask imported, no process started);
- ``workers=N`` (``auto``: one per core of this machine): a ``distributed.LocalCluster``
  of N worker processes with one thread each;
- ``scheduler=ADDRESS`` (or the environment variable :data:`ENV_SCHEDULER`): an
  existing Dask cluster (``dask scheduler`` and ``dask worker``, dask-jobqueue, ...).

A task is a module-level function and its arguments; it must be a pure function of
them (no state of the process it runs in), so that its result does not depend on where
it runs: results are the same for any number and kind of workers.  Data that many
tasks read (the runs of a diagnosis) are :meth:`Executor.scatter`-ed once and passed as
a handle: Dask sends them to each worker that needs them once per task graph, not with
every task.  A handle of a submitted task may be an argument of a later task (a
dependency, resolved where that task runs).

Progress: one record per completed task (at most every :data:`PROGRESS_SECONDS`) on the
``tacest.parallel`` logger, with the tasks done, the total and an estimate of the time
left; the command line draws it as one bar (cli/logs.py).  A task that raises ends the
run with its exception (the rest is cancelled); a worker that dies (a crash, the
out-of-memory killer, a lost machine) costs only its tasks, which the scheduler runs
again elsewhere, up to :data:`ALLOWED_FAILURES` times; Ctrl-C cancels every task and
raises KeyboardInterrupt (the command line exits with 130).

Tasks of one process never run at the same time (a worker with several threads runs
tacest's tasks one after another): the estimator's built solvers are cached per process
and are not made for concurrent use.  Give workers one thread each and as many
processes as cores (``dask worker --nthreads 1 --nworkers N``).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Optional

from tacest.errors import TacestError

log = logging.getLogger(__name__)

#: environment variable: address of a Dask scheduler used when neither --workers nor
#: --scheduler is given (e.g. tcp://10.0.0.5:8786)
ENV_SCHEDULER = "TACEST_SCHEDULER"
#: environment variable: the number of local workers (or ``auto``) when neither --workers
#: nor --scheduler is given and TACEST_SCHEDULER is not set
ENV_WORKERS = "TACEST_WORKERS"
#: a task whose worker died this many times is given up (an error); distributed's own
#: default (``distributed.scheduler.allowed-failures``), set here so that it is ours
ALLOWED_FAILURES = 3
#: s, longest wait for the scheduler at --scheduler
CONNECT_TIMEOUT = 30
#: s, shortest time between two progress records (the last task always reports)
PROGRESS_SECONDS = 1.0
#: the attribute of a progress record: {"done", "total", "elapsed", "eta"} (s)
PROGRESS_ATTR = "tacest_progress"


def machine_workers() -> int:
    """The cores this process may use (its CPU affinity), at least 1."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    return max(1, int(n))


def parse_workers(value) -> int:
    """The number of workers of ``value``: a positive integer, or ``auto`` (one per core
    of this machine, :func:`machine_workers`); TacestError otherwise."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return machine_workers()
    try:
        n = int(str(value).strip())
    except ValueError:
        n = 0
    if n < 1 or str(value).strip() in ("", "True", "False"):
        raise TacestError(f"--workers must be a positive integer or 'auto', got {value!r}")
    return n


@dataclass(frozen=True)
class ParallelSettings:
    """Where tasks run: ``workers`` processes of a local cluster (1: in this process), or
    the Dask scheduler at ``scheduler``."""

    workers: int = 1
    scheduler: Optional[str] = None

    @classmethod
    def resolve(cls, workers=None, scheduler=None, environ=None) -> "ParallelSettings":
        """The settings of a command's ``--workers`` and ``--scheduler`` (None: not
        given): an option given wins over the environment (:data:`ENV_SCHEDULER`, then
        :data:`ENV_WORKERS`); neither: in this process."""
        env = os.environ if environ is None else environ
        scheduler = (scheduler or "").strip() or None
        if workers is not None and scheduler:
            raise TacestError("--workers and --scheduler exclude each other: the workers of a cluster at "
                              "--scheduler are started with it (docs/parallel.md)")
        if scheduler:
            return cls(scheduler=scheduler)
        if workers is None:
            env_scheduler = env.get(ENV_SCHEDULER, "").strip()
            if env_scheduler:
                return cls(scheduler=env_scheduler)
            workers = env.get(ENV_WORKERS, "").strip() or 1
        return cls(workers=parse_workers(workers))

    @property
    def in_process(self) -> bool:
        return self.scheduler is None and self.workers == 1


class TaskFailed(Exception):
    """Internal: carries the exception of a task of the in-process executor to the
    tasks that depend on it."""


class _Task:
    """A task of the in-process executor: run once, when its result is first needed."""

    __slots__ = ("fn", "args", "kwargs", "key", "done", "value", "error", "seconds")

    def __init__(self, fn, args, kwargs, key):
        self.fn, self.args, self.kwargs, self.key = fn, args, kwargs, key
        self.done, self.value, self.error, self.seconds = False, None, None, 0.0


def _resolve(value):
    """``value`` with every in-process task handle in it (in tuples, lists and dict
    values) replaced by its result."""
    if isinstance(value, _Task):
        if value.error is not None:
            raise value.error
        if not value.done:
            raise TacestError(f"internal: task {value.key} used before it ran")
        return value.value
    if isinstance(value, tuple):
        return tuple(_resolve(v) for v in value)
    if isinstance(value, list):
        return [_resolve(v) for v in value]
    if isinstance(value, dict):
        return {k: _resolve(v) for k, v in value.items()}
    return value


#: held while a task runs on a worker: tacest's tasks of one process run one at a time
_TASK_LOCK = threading.Lock()
#: bytes: glibc's malloc thresholds in a worker (mallopt M_MMAP_THRESHOLD, M_TRIM_THRESHOLD):
#: the largest values of glibc's own dynamic default.  A Dask worker is started with
#: MALLOC_TRIM_THRESHOLD_=65536 (distributed's ``nanny.pre-spawn-environ``), which turns
#: that dynamic threshold off: every block over 128 kB of IPOPT's and CasADi's work
#: memory is then mapped and unmapped anew, and a fit took 20 % more time, in the kernel
#: (measured: 10 s of system time for 55 s of user time, against 1 s in one process)
MALLOC_MMAP_THRESHOLD = 32 << 20
MALLOC_TRIM_THRESHOLD = 64 << 20
_MALLOC_TUNED = []


def _tune_malloc():
    """Once per worker process: glibc's malloc thresholds as in a plain process (see
    MALLOC_MMAP_THRESHOLD); nothing where the C library is not glibc."""
    if _MALLOC_TUNED:
        return
    _MALLOC_TUNED.append(True)
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, MALLOC_MMAP_THRESHOLD)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, MALLOC_TRIM_THRESHOLD)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def _call(fn, args, kwargs):
    """How a task runs on a Dask worker: one tacest task per process at a time."""
    with _TASK_LOCK:
        _tune_malloc()
        return fn(*args, **kwargs)


def _versions() -> dict:
    """What a worker must share with the client for equal results."""
    import casadi
    import numpy

    import tacest

    return {"tacest": getattr(tacest, "__version__", "?"), "casadi": casadi.__version__, "numpy": numpy.__version__}


def _ignore_sigint(dask_worker=None):
    """Run in a local worker's main thread: Ctrl-C in the terminal reaches every process
    of its process group, the local workers too; the client alone handles it (cancels the
    graph, closes the cluster)."""
    import signal

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return True


def _sigint_plugin():
    """A WorkerPlugin running :func:`_ignore_sigint` on every worker of a local cluster,
    restarted ones too."""
    from distributed import WorkerPlugin

    class IgnoreSigint(WorkerPlugin):
        name = "tacest-ignore-sigint"

        def setup(self, worker):
            _ignore_sigint()

    return IgnoreSigint()


def format_seconds(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class Executor:
    """Runs tasks in this process or on a Dask cluster (module doc).  Use as a context
    manager (``with Executor(settings) as ex:``); :meth:`close` stops a local cluster.

    task_log : [(key, worker, seconds)] of the tasks that completed (the worker is
    ``in-process`` there), for summaries and benchmarks.
    """

    def __init__(self, settings: Optional[ParallelSettings] = None):
        self.settings = settings or ParallelSettings()
        self._client = None
        self._cluster = None
        self._outstanding = []  # in-process: _Task not yet run; Dask: futures not yet counted
        self._keys = set()
        self._total = 0
        self._done = 0
        self._t0 = time.perf_counter()
        self._last_report = -1e9
        self._stream_start = None
        self.task_log = []
        self.what = "tasks"

    # -- lifecycle ---------------------------------------------------------------------
    @property
    def distributed(self) -> bool:
        return not self.settings.in_process

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None and self._client is not None:
            self._cancel()
        self.close()
        return False

    def start(self):
        """Start the local cluster or connect to the scheduler (nothing in process)."""
        if not self.distributed or self._client is not None:
            return self
        import dask
        from distributed import Client

        # local workers get no malloc trim threshold (see MALLOC_MMAP_THRESHOLD)
        dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                         "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None})
        _quiet_distributed(logging.ERROR)  # tacest's own lines say what happens
        if self.settings.scheduler:
            try:
                self._client = Client(self.settings.scheduler, timeout=CONNECT_TIMEOUT, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise TacestError(f"--scheduler {self.settings.scheduler}: no Dask scheduler answered "
                                  f"within {CONNECT_TIMEOUT} s ({exc.__class__.__name__})") from None
            kind = f"the Dask cluster at {self.settings.scheduler}"
        else:
            self._start_local()
            kind = f"a local Dask cluster of {self.settings.workers} worker processes"
        self._check_workers()
        try:  # the scheduler records the task stream from now on (who ran what, how long)
            self._stream_start = time.time()
            self._client.get_task_stream(count=1)
        except Exception:  # noqa: BLE001 - a summary only
            self._stream_start = None
        link = self._dashboard()
        log.info(f"dask: {kind}, {len(self.workers())} worker(s)"
                 + (f", dashboard {link}" if link else ", no dashboard (pip install bokeh)"))
        return self

    def _start_local(self):
        from distributed import Client, LocalCluster

        dashboard = ":0" if _has_bokeh() else None
        self._cluster = LocalCluster(n_workers=self.settings.workers, threads_per_worker=1, processes=True,
                                     dashboard_address=dashboard, silence_logs=logging.CRITICAL)
        self._client = Client(self._cluster, set_as_default=False)
        self._client.register_plugin(_sigint_plugin())

    def _check_workers(self):
        """TacestError unless every worker runs the tacest, CasADi and numpy of this
        process (or there are no workers yet: a cluster may start them later)."""
        mine = _versions()
        try:
            theirs = self._client.run(_versions)
        except Exception as exc:  # noqa: BLE001 - a worker that cannot import tacest
            raise TacestError(f"a Dask worker cannot run tacest's tasks ({exc.__class__.__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''}); install this tacest on every "
                              "worker (docs/parallel.md)") from None
        for worker, v in theirs.items():
            if v != mine:
                diff = ", ".join(f"{k} {v.get(k)} (here {mine[k]})" for k in mine if v.get(k) != mine[k])
                raise TacestError(f"Dask worker {worker} runs {diff}; every worker needs the same versions for "
                                  "equal results (docs/parallel.md)")

    def _dashboard(self) -> str:
        try:
            return self._client.dashboard_link if self._client.scheduler_info().get("services", {}).get(
                "dashboard") else ""
        except Exception:  # noqa: BLE001 - the address is a convenience
            return ""

    def workers(self) -> list:
        """Addresses of the workers (``["in-process"]`` in this process)."""
        if self._client is None:
            return ["in-process"]
        return sorted(self._client.scheduler_info(n_workers=-1).get("workers", {}))

    def close(self):
        """Log the tasks per worker, then close the client and stop a local cluster."""
        if self._client is None:
            return
        try:
            counts = self.tasks_per_worker()
            if counts:
                log.info(f"dask: {sum(counts.values())} tasks ran on {len(counts)} worker(s): "
                         + ", ".join(f"{w} {n}" for w, n in sorted(counts.items())))
        finally:
            client, cluster = self._client, self._cluster
            self._client = self._cluster = None
            _quiet_distributed(logging.CRITICAL + 1)  # closing connections is not news
            try:
                client.close()
            finally:
                if cluster is not None:
                    cluster.close()

    def tasks_per_worker(self) -> dict:
        """{worker address: tasks of this executor it computed} (the scheduler's task
        stream; {"in-process": n} in this process)."""
        if self._client is None:
            return {"in-process": len(self.task_log)} if self.task_log else {}
        self._refresh_task_log()
        out = {}
        for _, worker, _ in self.task_log:
            out[worker] = out.get(worker, 0) + 1
        return out

    def _refresh_task_log(self):
        if self._client is None or self._stream_start is None:
            return
        try:
            stream = self._client.get_task_stream(start=self._stream_start)
        except Exception:  # noqa: BLE001 - a summary only
            return
        log_ = []
        for rec in stream:
            key = rec.get("key")
            if key not in self._keys:
                continue
            compute = sum(s["stop"] - s["start"] for s in rec.get("startstops", ()) if s.get("action") == "compute")
            log_.append((key, rec.get("worker", "?"), compute))
        self.task_log = log_

    # -- tasks -------------------------------------------------------------------------
    def scatter(self, value):
        """A handle of ``value`` for tasks' arguments: sent once to each worker that
        needs it (the value itself in this process)."""
        if self._client is None:
            return value
        return self._client.scatter([value], hash=False)[0]

    def submit(self, fn, *args, name: str = "task", priority: int = 0, **kwargs):
        """Submit ``fn(*args, **kwargs)`` (a module-level function; handles of earlier
        tasks and scattered data among the arguments are replaced by their values);
        returns its handle.  ``name`` prefixes the task's key (the dashboard groups by
        it); ``priority``: higher runs first among tasks that are ready."""
        key = f"tacest-{name}-{uuid.uuid4().hex}"
        self._keys.add(key)
        self._total = max(self._total, self._done + len(self._outstanding) + 1)
        if self._client is None:
            task = _Task(fn, args, kwargs, key)
            self._outstanding.append(task)
            return task
        fut = self._client.submit(_call, fn, args, kwargs, key=key, pure=False, priority=priority)
        self._outstanding.append(fut)
        return fut

    def plan(self, total: int, what: str = "tasks", reset: bool = True):
        """Start the progress count of a piece of work of ``total`` tasks (the ones to be
        submitted from now on); more tasks than that raise the total.  ``reset`` False:
        the same piece of work, whose total is now known better (the tasks done so far
        count in ``total``)."""
        if reset:
            self._done = 0
            self._t0 = time.perf_counter()
            self._last_report = -1e9
        self._total = max(int(total), self._done + len(self._outstanding))
        self.what = what

    def result(self, handle):
        """The result of one task (waiting for it)."""
        return self.gather([handle])[0]

    def gather(self, handles) -> list:
        """The results of ``handles`` (waiting for them, and counting every task that
        completes meanwhile); the first task that raised ends the wait with its
        exception, every other task cancelled."""
        handles = list(handles)
        if self._client is None:
            return self._gather_in_process(handles)
        return self._gather_dask(handles)

    def _gather_in_process(self, handles):
        needed = {id(h) for h in handles if isinstance(h, _Task)}
        while needed & {id(t) for t in self._outstanding}:
            task = self._outstanding.pop(0)
            t0 = time.perf_counter()
            try:
                args, kwargs = _resolve(task.args), _resolve(task.kwargs)
                task.value = task.fn(*args, **kwargs)
            except Exception as exc:
                task.error = exc
                self._outstanding.clear()
                raise
            task.done = True
            task.seconds = time.perf_counter() - t0
            self.task_log.append((task.key, "in-process", task.seconds))
            self._count()
        return [_resolve(h) for h in handles]

    def _gather_dask(self, handles):
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        wanted = {h.key for h in handles if hasattr(h, "key") and h.key in self._keys}
        try:
            pending = [f for f in self._outstanding if f.key in wanted]
            if pending:
                for fut in as_completed(list(self._outstanding), loop=self._client.loop):
                    self._outstanding.remove(fut)
                    if fut.status == "error":
                        fut.result()  # raises the task's exception
                    if fut.status == "cancelled":
                        raise TacestError(f"task {fut.key} was cancelled by the cluster")
                    self._count()
                    wanted.discard(fut.key)
                    if not wanted:
                        break
            return self._client.gather(handles)
        except KilledWorker as exc:
            self._cancel()
            raise TacestError(f"a task lost its worker more than {ALLOWED_FAILURES} times (out of memory? "
                              f"see docs/parallel.md, 'Memory'): {str(exc).splitlines()[0]}") from None
        except BaseException:
            self._cancel()
            raise

    def _cancel(self):
        """Cancel every task not yet gathered."""
        if self._client is None or not self._outstanding:
            return
        futures, self._outstanding = list(self._outstanding), []
        try:
            self._client.cancel(futures, force=True)
        except Exception:  # noqa: BLE001 - the cluster is closed next anyway
            pass

    def _count(self):
        self._done += 1
        self._total = max(self._total, self._done)
        now = time.perf_counter()
        if self._done < self._total and now - self._last_report < PROGRESS_SECONDS:
            return
        self._last_report = now
        elapsed = now - self._t0
        eta = elapsed / self._done * (self._total - self._done)
        log.info(f"{self.what}: {self._done}/{self._total} done ({self._done / self._total:.0%}), "
                 f"{format_seconds(elapsed)} elapsed, about {format_seconds(eta)} left",
                 extra={PROGRESS_ATTR: {"done": self._done, "total": self._total, "elapsed": elapsed, "eta": eta,
                                        "what": self.what}})


def _quiet_distributed(level: int):
    """Set distributed's loggers (and tornado's, which it uses) to ``level``: they log
    to stderr through handlers of their own."""
    for name in list(logging.root.manager.loggerDict) + ["distributed", "tornado"]:
        if name.split(".")[0] in ("distributed", "tornado"):
            logging.getLogger(name).setLevel(level)


def _has_bokeh() -> bool:
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return False
    return True


def open_executor(workers=None, scheduler=None) -> Executor:
    """An (unstarted) Executor for a command's ``--workers`` and ``--scheduler``
    (ParallelSettings.resolve); use it as a context manager."""
    return Executor(ParallelSettings.resolve(workers, scheduler))


# ---------------------------------------------------------------------------------------
# forked copies of this process (the starts of one estimate: estimation.solver)

#: the forked workers' job (fork_map): set in the parent before they are forked, so that
#: they inherit it (with the built NLP it closes over) instead of receiving it pickled
_FORK_JOB = None
#: exception types a job's failure is returned as (an entry of fork_map's list)
_FORK_RETURNED: tuple = ()
#: linear solvers that run OpenMP threads: a forked child of a process that used them can
#: deadlock, so their fits are never forked
OPENMP_LINEAR_SOLVERS = ("spral", "ma86", "ma97")


def _fork_worker_init():
    import signal

    # Ctrl-C is the parent's to handle: it kills the workers (no traceback from each)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _fork_call(k):
    try:
        return _FORK_JOB(k)
    except _FORK_RETURNED as exc:
        return exc


def fork_processes(workers: int, jobs: int) -> int:
    """How many forked processes run ``jobs`` independent jobs: ``workers`` (0: one per
    core this process may use, :func:`machine_workers`), at most one per job; 1 where
    forking is not safe or not possible: not Linux, a daemonic process (a Dask worker),
    or a process running other threads (a child forked beside them can inherit a held
    lock)."""
    import multiprocessing as mp
    import sys

    if (jobs < 2 or not sys.platform.startswith("linux") or mp.current_process().daemon
            or threading.active_count() > 1):
        return 1
    return max(1, min(int(workers) or machine_workers(), int(jobs)))


def fork_map(job, n: int, processes: int, returned: tuple = ()) -> list:
    """[job(0), ..., job(n - 1)] computed by ``processes`` forked copies of this process
    (each inherits everything ``job`` needs: nothing but k and the results is pickled);
    an exception of a type in ``returned`` is returned as the job's entry, any other is
    raised here as soon as it arrives.  A worker that dies (killed, out of memory) is a
    TacestError.  On any exception here, Ctrl-C included (the workers ignore SIGINT: the
    parent handles it), the workers are killed before it is raised: none goes on
    computing or writing."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    global _FORK_JOB, _FORK_RETURNED
    _FORK_JOB, _FORK_RETURNED = job, tuple(returned)
    pool = ProcessPoolExecutor(processes, mp_context=mp.get_context("fork"), initializer=_fork_worker_init)
    try:
        futures = [pool.submit(_fork_call, k) for k in range(n)]  # the workers fork at the first
        done, _ = wait(futures, return_when=FIRST_EXCEPTION)
        for f in done:  # an error is raised as soon as it arrives, not after the jobs before it
            if f.exception() is not None:
                raise f.exception()
        out = [f.result() for f in futures]
    except BrokenProcessPool:
        _kill_workers(pool)
        raise TacestError("a worker process ended without a result (killed, or out of memory?); "
                          "[solver] start_workers = 1 runs the starts in this process") from None
    except BaseException:
        _kill_workers(pool)
        raise
    finally:
        _FORK_JOB, _FORK_RETURNED = None, ()
    pool.shutdown()
    return out


def forked_map(fun, items, workers: int = 0) -> list:
    """[fun(x) for x in items]: by :func:`fork_processes` (``workers``, 0: one per core)
    forked copies of this process where that is safe, else here.  ``fun`` must give the
    same for an item wherever it runs (the forked copies' changes to their own state
    are lost)."""
    items = list(items)
    processes = fork_processes(int(workers), len(items))
    if processes < 2:
        return [fun(x) for x in items]
    return fork_map(lambda k: fun(items[k]), len(items), processes)


def _kill_workers(pool) -> None:
    """Kill a ProcessPoolExecutor's workers now (Python 3.11 has no public way) and let
    it go without waiting for their jobs."""
    for proc in list(getattr(pool, "_processes", {}).values()):
        proc.kill()
    pool.shutdown(wait=True, cancel_futures=True)
