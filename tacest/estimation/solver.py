"""The one staged solve: IPOPT on a problem built once per structure, run through a plan
of stages (impulses alone, then the homotopy), with warm starts, pinned parameters,
iteration budgets, one retry, restarts from other starts, and one status policy.

Used by the 2-D and 3-D estimators, the shooting baseline and every diagnosis fit.

Status policy (:func:`run_stages`):

- an IPOPT status in :data:`SUCCESS_STATUSES` is a solution;
- an interrupt (Ctrl-C during a solve, noted by :func:`tacest.interrupt.watch_interrupts`
  or reported by IPOPT as ``User_Requested_Stop``) ends everything at once
  (KeyboardInterrupt, :func:`tacest.interrupt.raise_if_interrupted`), never a failed
  stage that the caller might step over;
- an intermediate stage (impulses alone, an early homotopy stage) only prepares the
  next: its iterate is used whether or not IPOPT met its tolerance within the stage's
  budget, unless its status is in :data:`FATAL_STATUSES`;
- the final stage must succeed; with ``accept_budget`` a final stage that used up its
  iteration or time budget keeps its last iterate and its status (success False);
- a final stage whose step computation failed (:data:`RETRY_STATUSES`) is redone once
  from its last iterate with the Gauss–Newton model and the ridge :data:`RETRY_RIDGE`;
- a start's final stage that stays far above the best fit so far is stopped
  (:data:`ABANDON_RULE`, ``abandon_above``): StartAbandoned, which
  :func:`solve_from_starts` records as an abandoned attempt.

A failure raises SolveFailedError with IPOPT's status; nothing is reported as an
estimate then.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import casadi as ca
import numpy as np

from tacest.errors import SolveFailedError
from tacest.parallel import fork_map, fork_processes
from tacest.interrupt import raise_if_interrupted, watch_interrupts

log = logging.getLogger(__name__)

#: IPOPT statuses that count as a solution
SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: statuses after which not even an intermediate iterate can be used
FATAL_STATUSES = ("Invalid_Number_Detected", "Error_In_Step_Computation", "Insufficient_Memory",
                  "Internal_Error", "Invalid_Problem_Definition", "Invalid_Option", "Unrecoverable_Exception",
                  "NonIpopt_Exception_Thrown")
#: statuses of a solve that ran out of its iteration or time budget: with
#: ``accept_budget`` its last iterate is used (and reported with this status)
BUDGET_STATUSES = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded", "Stopped_Stalled")
#: tacest's status of a final stage stopped by :data:`STALL_RULE` (not IPOPT's): a budget
#: status (its last iterate is kept, competes by its objective, never ends a search)
STALLED_STATUS = "Stopped_Stalled"
#: statuses of a final stage after which the stage is redone once from its last iterate
#: with the Gauss–Newton Hessian and ridge RETRY_RIDGE
RETRY_STATUSES = ("Error_In_Step_Computation", "Restoration_Failed")
#: Levenberg–Marquardt ridge (scaled units) of that retry: the 2-D estimator's default
#: before it was lowered to 0.05 for speed; it keeps the steps local where IPOPT failed to
#: step
RETRY_RIDGE = 1.0
#: tacest's status of a final stage stopped by :data:`ABANDON_RULE` (not IPOPT's)
ABANDONED_STATUS = "Abandoned_Far_Above_Best"
#: when a start is hopeless: (iterations, ratio) pairs; a final stage whose lowest
#: objective after at least ``iterations`` of its iterations is above ``ratio`` times the
#: best fit's so far is stopped (its fit could not be kept).  Measured on the final
#: stages of every start of 20 dynamic 2-D recordings (boxes with and without force,
#: tuning seeds 0-9, 55 final stages): the final objective was at least 1/4.7 of the
#: stage's lowest objective of its first 20 iterations, 1/2.6 of that of its first 30,
#: 1/1.9 of that of its first 100; each ratio here is about twice that, so no stage of
#: those recordings was stopped that would have ended below the best.  The lowest
#: objective, not the last: IPOPT's filter accepts single iterates 7x above their
#: neighbours (a restart at 323 stepped to 2421 and ended at 317, below the best 402).
#: It saved 79 s of 806 there, all on the 7 recordings that needed restarts
#: (a restart that took 25 s stopped after 20 iterations).
ABANDON_RULE = ((20, 10.0), (30, 5.0), (100, 3.0))
#: when a final stage has stalled: (from, window, gain): from iteration ``from`` on, a
#: stage whose lowest objective fell by less than ``gain`` of itself over the last
#: ``window`` iterations is stopped and its last iterate kept as if it had used up its
#: budget (:data:`STALLED_STATUS`; only where the caller keeps budget fits; the
#: search over starts resumes a stalled fit that it keeps: :func:`solve_from_starts`).
#: Measured on the final stages of every start of 60 2-D recordings (boxes with and
#: without force, polygons; gentle and dynamic; tuning seeds 0-9; 181 final stages):
#: 14 of the 15 that ran to the 400-iteration budget had stalled (at iterations
#: 180-380; a gentle box's: 4116 at the stall, 4116 at 400 iterations, 21 s, a wrong
#: basin 100x above the fit the restarts then found); no converged stage of a box or a
#: gentle polygon had stalled before converging, but dynamic polygons' stages crawl for
#: up to 390 iterations before converging up to 8 % lower (hence the resume;
#: docs/estimation.md, "Stalled starts are set aside").
STALL_RULE = (150, 100, 0.01)
#: half-width (scaled units, relative to max(1, |value|)) of the interval that holds a
#: variable fixed (:func:`pin`).  IPOPT removes variables with equal bounds; with the
#: Gauss–Newton Hessian model some such problems failed at iteration 0
#: (Error_In_Step_Computation), while the same problems with the parameters kept as
#: variables in an interval of 2e-9 solve.  1e-9 of a scaled parameter (O(1)) is far
#: below anything the data resolve.
PIN_HALF_WIDTH = 1e-9
#: a variable whose bounds are closer than this (scaled units) counts as held (the
#: information matrix gives it no row)
HELD_WIDTH = 1e-8


@dataclass
class StageInfo:
    name: str
    status: str
    iterations: int
    wall_time: float
    objective: float


@dataclass
class SolveOutcome:
    """What IPOPT returned over all stages of one staged solve."""

    z: np.ndarray
    lam_g: Optional[np.ndarray]
    lam_x: Optional[np.ndarray]
    status: str
    success: bool
    iterations: int
    wall_time: float
    objective: float
    stages: list = field(default_factory=list)


@dataclass(frozen=True)
class Stage:
    """One IPOPT solve of a staged fit: the homotopy's settings (epsilon, complementarity
    and dynamics multipliers), whether only the contact impulses (and states) are free,
    the Hessian model, the iteration budget, whether it is the final stage, and IPOPT's
    acceptable tolerance (None: the problem's)."""

    label: str
    eps: float
    comp_mult: float
    dyn_mult: float
    impulses_only: bool
    hessian: str
    max_iter: int
    final: bool
    acceptable_tol: Optional[float] = None


def plan_stages(homotopy, hessian: str, max_iter: int, stage_max_iter: int, impulses_first: bool = True,
                last_only: bool = False, acceptable_tol: Optional[float] = None) -> list:
    """The stages of one staged solve.

    homotopy : [[epsilon, complementarity multiplier, dynamics multiplier], ...];
    hessian : "gauss-newton", "exact" or "gauss-newton-then-exact" (the exact model in
        the final stage when there are two or more homotopy stages);
    impulses_first : a first stage with everything but the contact impulses held (at
        the first homotopy stage's settings: a convex least-squares problem, so that
        every later stage starts from a physically consistent point);
    last_only : only the last homotopy stage (a warm start: z0 is already a solution of
        a nearby problem);
    acceptable_tol : IPOPT's acceptable tolerance (scaled KKT error) of every stage
        (None: the problem's, ipopt_options and its nlpsol_options).
    """
    hom = [tuple(float(x) for x in s) for s in homotopy]
    if last_only:
        hom = hom[-1:]
    stages = []
    if impulses_first:
        stages.append(Stage("impulses", *hom[0], impulses_only=True,
                            hessian="gauss-newton" if hessian == "gauss-newton-then-exact" else hessian,
                            max_iter=stage_max_iter, final=False, acceptable_tol=acceptable_tol))
    for k, (eps, w, wd) in enumerate(hom):
        final = k == len(hom) - 1
        mode = hessian
        if mode == "gauss-newton-then-exact":
            mode = "exact" if final and len(hom) > 1 else "gauss-newton"
        stages.append(Stage(f"homotopy {k + 1}/{len(hom)}", eps, w, wd, impulses_only=False, hessian=mode,
                            max_iter=max_iter if final else stage_max_iter, final=final,
                            acceptable_tol=acceptable_tol))
    return stages


def pin(lbx, ubx, index, values):
    """Hold the variables ``index`` at ``values`` (scaled) in an interval of
    ±PIN_HALF_WIDTH·max(1, |value|), not by equal bounds (see PIN_HALF_WIDTH); lbx, ubx
    are changed in place and returned."""
    values = np.asarray(values, float)
    half = PIN_HALF_WIDTH * np.maximum(1.0, np.abs(values))
    lbx[index] = values - half
    ubx[index] = values + half
    return lbx, ubx


def held(lbx, ubx) -> np.ndarray:
    """(n,) bool: the variables held by their bounds (pinned or fixed)."""
    return np.asarray(ubx, float) - np.asarray(lbx, float) <= HELD_WIDTH


class StartAbandoned(SolveFailedError):
    """A start's final stage stopped by :data:`ABANDON_RULE`: its fit could not be
    kept (solve_from_starts records it as an abandoned attempt)."""


class BestSoFar:
    """The lowest objective of the fits finished so far that could be kept, shared with
    the forked processes that solve starts at once (a double in shared memory, created
    before they fork): a fit finished in one is seen at the next IPOPT iteration of the
    others.  Two fits offered at the same instant may leave the higher of the two (the
    minimum is not atomic): a higher threshold only stops less."""

    def __init__(self):
        import multiprocessing as mp

        self._shared = mp.RawValue("d", float("inf"))

    @property
    def value(self) -> float:
        return float(self._shared.value)

    def offer(self, objective: float):
        if np.isfinite(objective) and objective < self._shared.value:
            self._shared.value = float(objective)


def stalled(lowest: list) -> bool:
    """Whether a final stage whose lowest objective after each of its iterations so far
    is ``lowest`` (non-increasing, one entry per iteration) has stalled (:data:`STALL_RULE`)."""
    start, window, gain = STALL_RULE
    it = len(lowest) - 1
    if it < max(start, window) or not np.isfinite(lowest[it - window]):
        return False
    return lowest[it - window] - lowest[it] < gain * abs(lowest[it])


def best_value(best) -> float:
    """The objective of ``best`` (a number, or a BestSoFar's current value)."""
    return best.value if isinstance(best, BestSoFar) else float(best)


def hopeless(iteration: int, lowest: float, best: float) -> bool:
    """Whether a final stage whose lowest objective after ``iteration`` iterations is
    ``lowest`` is stopped beside a best fit of objective ``best`` (:data:`ABANDON_RULE`;
    never where best is not a finite positive number)."""
    if not (np.isfinite(best) and best > 0):
        return False
    return any(iteration >= n and lowest > ratio * best for n, ratio in ABANDON_RULE)


class _Progress(ca.Callback):
    """IPOPT iteration callback: one progress line (log level INFO) every ``every``
    iterations, and the stop of a hopeless stage (``abandon_above``: the best fit's
    objective so far, :func:`hopeless`; ``abandoned`` says it happened) or of a stalled
    one (``stop_stalled``, :func:`stalled`; ``stalled`` says it happened).  A Ctrl-C that
    arrives here stops IPOPT (``User_Requested_Stop``); :meth:`BuiltSolver.solve` turns
    that into KeyboardInterrupt (tacest.interrupt)."""

    def __init__(self, nx, ng, every):
        ca.Callback.__init__(self)
        self.nx, self.ng = nx, ng
        self.lbg = self.ubg = np.zeros(ng)
        self.every = max(1, int(every))
        self.label = ""
        self.it = 0
        self.abandon_above = float("inf")
        self.lowest = float("inf")
        self.abandoned = False
        self.stop_stalled = False
        self.stalled = False
        self.lowest_history = []
        self.construct("progress", {"enable_fd": False})

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        n = ca.nlpsol_out(i)
        if n == "f":
            return ca.Sparsity.scalar()
        if n in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if n in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def eval(self, arg):
        try:
            f = float(arg[ca.nlpsol_out().index("f")])
            if self.it % self.every == 0 and log.isEnabledFor(logging.INFO):
                g = np.asarray(arg[ca.nlpsol_out().index("g")]).reshape(-1)
                inf = float(np.max(np.concatenate([[0.0], self.lbg - g, g - self.ubg]))) if g.size else 0.0
                log.info(f"  {self.label} iter {self.it:4d}  objective {f:12.5e}  infeasibility {inf:9.2e}")
            if np.isfinite(f):
                self.lowest = min(self.lowest, f)
            if hopeless(self.it, self.lowest, best_value(self.abandon_above)):
                self.abandoned = True
                return [1]  # IPOPT stops: User_Requested_Stop, which solve() reads as abandoned
            if self.stop_stalled:
                self.lowest_history.append(self.lowest)
                if stalled(self.lowest_history):
                    self.stalled = True
                    return [1]  # User_Requested_Stop, which solve() reads as stalled
            self.it += 1
        except KeyboardInterrupt:
            # a Ctrl-C handled here (the next Python code IPOPT runs): ask IPOPT to stop
            # (a nonzero return: User_Requested_Stop) rather than let the exception
            # cross CasADi, which prints its traceback; the interrupt watch has noted it
            return [1]
        return [0]


#: IPOPT options of every staged solve (a problem may override some: nlpsol_options)
def ipopt_options(solver_config, max_iter) -> dict:
    """IPOPT options from the [solver] settings (tacest.estimation.config.Solver)."""
    sc = solver_config
    return {
        "print_level": 0,
        "sb": "yes",
        "linear_solver": sc.linear_solver,
        "tol": sc.tol,
        "acceptable_tol": sc.acceptable_tol,
        "acceptable_iter": 5,
        # An acceptable point: constraints (kinematics in object lengths per second,
        # lifted parameters relative) met to 1e-4, and the objective, a chi-square sum of
        # thousands of whitened residuals, changing by less than 1e-3 of itself per
        # iteration for acceptable_iter iterations.  The last iterations mostly slide
        # along the weakly determined mass–friction valley (only mu·m·g is seen in
        # steady sliding), which the information matrix reports; shape and trajectory
        # have long settled by then.
        "acceptable_constr_viol_tol": 1e-4,
        # Complementarity of the bounds (lambda_n >= 0) is x_i z_i in objective units
        # (unscaled: half a chi-square): with the monotone barrier held at mu_init it
        # stays near mu / (IPOPT's objective scaling, ~1e-3..1e-2), ~3e-3.  0.1 of an
        # objective unit is far below what the data resolve (one whitened residual of
        # 0.45 sigma); 1e-3 kept converged fits iterating to the iteration limit.
        "acceptable_compl_inf_tol": 0.1,
        "acceptable_obj_change_tol": 1e-3,
        "max_iter": int(max_iter),
        "max_cpu_time": sc.max_cpu_time,
        # every stage starts from a consistent point (see plan_stages): a small barrier
        # parameter and bound push keep IPOPT from pushing contact impulses off their
        # bounds into the interior
        "mu_strategy": "monotone",
        "mu_init": float(sc.barrier),
        "bound_push": 1e-8,
        "bound_frac": 1e-8,
        "warm_start_init_point": "yes",
        "warm_start_bound_push": 1e-8,
        "warm_start_bound_frac": 1e-8,
        "warm_start_mult_bound_push": 1e-8,
    }


class BuiltSolver:
    """A problem and its IPOPT solvers (one per Hessian model and budget), built once
    per structure.  The problem supplies ``nlp`` ({x, p, f, g}), ``lbg``/``ubg``,
    ``n_z``, ``hess_lag`` ({mode: Function}; a mode "limited-memory" needs none) and
    optionally ``nlpsol_options`` (overrides, ``{"ipopt": {...}}`` included)."""

    def __init__(self, problem, config):
        self.problem = problem
        self.config = config
        self.progress = _Progress(problem.n_z, problem.g.shape[0], config.solver.print_every)
        self.solvers = {}

    def _make(self, mode, max_iter, acceptable_tol=None):
        opts = {"expand": False, "print_time": False, "iteration_callback": self.progress,
                "ipopt": ipopt_options(self.config.solver, max_iter)}
        if mode == "limited-memory":
            opts["ipopt"]["hessian_approximation"] = "limited-memory"
        else:
            opts["hess_lag"] = self.problem.hess_lag[mode]
        extra = dict(getattr(self.problem, "nlpsol_options", None) or {})
        opts["ipopt"].update(extra.pop("ipopt", {}))
        opts.update(extra)
        if acceptable_tol is not None:
            opts["ipopt"]["acceptable_tol"] = float(acceptable_tol)
        return ca.nlpsol(f"tacest_nlp_{mode.replace('-', '_')}", "ipopt", self.problem.nlp, opts)

    def solve(self, z0, p, lbx, ubx, lam_x0=None, lam_g0=None, label="", hessian="gauss-newton", max_iter=None,
              acceptable_tol=None, abandon_above=float("inf"), stop_stalled=False):
        """One IPOPT solve; returns (solution dict, StageInfo).  acceptable_tol : IPOPT's
        acceptable tolerance (None: the problem's); abandon_above : the best fit's
        objective so far (a number or a BestSoFar, read at every iteration), beside
        which a hopeless solve is stopped (:func:`hopeless`; status ABANDONED_STATUS);
        stop_stalled : stop a stalled solve (:func:`stalled`; status STALLED_STATUS,
        its last iterate returned).
        An interrupt during the solve raises KeyboardInterrupt
        (:func:`tacest.interrupt.raise_if_interrupted`)."""
        max_iter = self.config.solver.max_iter if max_iter is None else int(max_iter)
        key = (hessian, max_iter, acceptable_tol)
        if key not in self.solvers:
            self.solvers[key] = self._make(hessian, max_iter, acceptable_tol)
        solver = self.solvers[key]
        pr = self.problem
        self.progress.label = label
        self.progress.lbg, self.progress.ubg = pr.lbg, pr.ubg
        self.progress.it = 0
        self.progress.lowest = float("inf")
        self.progress.abandon_above = abandon_above
        self.progress.abandoned = False
        self.progress.stop_stalled = bool(stop_stalled)
        self.progress.stalled = False
        self.progress.lowest_history = []
        args = dict(x0=z0, p=p, lbx=lbx, ubx=ubx, lbg=pr.lbg, ubg=pr.ubg)
        if lam_x0 is not None:
            args["lam_x0"] = lam_x0
        if lam_g0 is not None and np.size(lam_g0) == pr.g.shape[0]:
            args["lam_g0"] = lam_g0
        t0 = time.perf_counter()
        with watch_interrupts() as watch:
            sol = solver(**args)
        wall = time.perf_counter() - t0
        st = solver.stats()
        status = st.get("return_status", "unknown")
        if self.progress.abandoned and not watch.interrupted:
            status = ABANDONED_STATUS
        elif self.progress.stalled and not watch.interrupted:
            status = STALLED_STATUS
        raise_if_interrupted(status, watch)
        return sol, StageInfo(name=label, status=status, iterations=int(st.get("iter_count", 0)), wall_time=wall,
                              objective=float(sol["f"]))


#: built solvers a process keeps (2-D and shooting; 3-D: one).  One 2-D diagnosis of a
#: 7-poke run (every candidate, 3 folds) meets 64 structures in 157 fits, in the order of
#: its candidates: keeping the 16 most recently used rebuilds 3 of them (12: 43, 8: 59)
SOLVER_CACHE_LIMIT = 16


class SolverCache:
    """Built solvers by structure key, at most ``limit`` at a time: the least recently
    used one is dropped first (a built 2-D solver of a 10 s run holds about 80 MB of
    CasADi graphs and IPOPT and MUMPS workspaces; an unbounded cache held every
    structure a process ever met: 5.3 GB after one diagnosis, and a closed loop of
    diagnoses was killed for memory after four)."""

    def __init__(self, limit: Optional[int] = None):
        if limit is not None and int(limit) < 1:
            raise ValueError(f"SolverCache: limit {limit} < 1")
        self.limit = limit
        self._items: dict = {}

    def get(self, key, build: Callable[[], object]):
        """The item of ``key``, built by ``build()`` if not kept (a built solver, or any
        costly structure: the planner keeps its expected-information models here)."""
        if key in self._items:
            self._items[key] = self._items.pop(key)  # now the most recently used
            return self._items[key]
        item = build()  # first: a build that raises leaves the cache as it was
        if self.limit is not None:
            while len(self._items) >= self.limit:
                self._items.pop(next(iter(self._items)))
        self._items[key] = item
        return item

    def __len__(self) -> int:
        return len(self._items)


def stage_failure(info: StageInfo) -> SolveFailedError:
    """The error of a stage that did not succeed."""
    return SolveFailedError(f"IPOPT failed in stage {info.name!r}: {info.status} after {info.iterations} "
                            "iterations (no estimate written)")


def check_success(info: StageInfo):
    if info.status not in SUCCESS_STATUSES:
        raise stage_failure(info)


def run_stages(built: BuiltSolver, z0, stages: list, params_of: Callable, bounds_of: Callable,
               prepare: Callable = None, accept_budget: bool = False, lam_x0=None, lam_g0=None,
               abandon_above=float("inf"), stop_stalled=False) -> SolveOutcome:
    """Run a plan of stages (:func:`plan_stages`) from z0 (scaled) under the status
    policy of the module docstring.

    params_of(stage, retry=False) -> p : the parameter vector of a stage (``retry``: with
        the Levenberg–Marquardt ridge max(RETRY_RIDGE, the configured one));
    bounds_of(stage, z) -> (lbx, ubx) : the bounds of a stage at z (an impulses-only
        stage holds everything else at z);
    prepare(stage, z, p) -> z : called before each stage (e.g. settle the effects'
        states before the impulses stage), or None;
    lam_x0, lam_g0 : multipliers that warm-start the first stage that frees everything;
    abandon_above : the best fit's objective so far (a number, or solve_from_starts'
        BestSoFar): a final stage that stays far above it is stopped (:func:`hopeless`)
        and StartAbandoned raised;
    stop_stalled : with ``accept_budget``, a final stage that has stalled
        (:func:`stalled`) is stopped and its last iterate kept as a budget fit
        (STALLED_STATUS).
    """
    stop_stalled = bool(stop_stalled and accept_budget)
    z = np.asarray(z0, float).copy()
    lam_x, lam_g = lam_x0, lam_g0
    infos = []
    for stage in stages:
        p = params_of(stage)
        if prepare is not None:
            z = prepare(stage, z, p)
        lbx, ubx = bounds_of(stage, z)
        z = np.clip(z, lbx, ubx)
        warm = not stage.impulses_only
        sol, info = built.solve(z, p, lbx, ubx, lam_x if warm else None, lam_g if warm else None,
                                label=stage.label, hessian=stage.hessian, max_iter=stage.max_iter,
                                acceptable_tol=stage.acceptable_tol,
                                abandon_above=abandon_above if stage.final else float("inf"),
                                stop_stalled=stop_stalled and stage.final)
        log.info(f"stage {stage.label}: {info.status}, {info.iterations} iterations, "
                 f"objective {info.objective:.6g}, {info.wall_time:.1f} s")
        x_last = np.asarray(sol["x"]).reshape(-1)
        if stage.final and info.status in RETRY_STATUSES and np.all(np.isfinite(x_last)):
            # IPOPT could not compute a step (a KKT system it could not correct): redo the
            # stage once from its last iterate with the Gauss–Newton model and a larger
            # Levenberg–Marquardt ridge (shorter, safer steps), same budget
            infos.append(info)
            label = stage.label + " (retry)"
            sol, info = built.solve(np.clip(x_last, lbx, ubx), params_of(stage, retry=True), lbx, ubx,
                                    label=label, hessian="gauss-newton", max_iter=stage.max_iter,
                                    acceptable_tol=stage.acceptable_tol, abandon_above=abandon_above,
                                    stop_stalled=stop_stalled)
            info.name = label
            log.info(f"stage {label}: {info.status}, {info.iterations} iterations, "
                     f"objective {info.objective:.6g}, {info.wall_time:.1f} s")
        if info.status == ABANDONED_STATUS:
            raise StartAbandoned(f"abandoned in stage {info.name!r} after {info.iterations} iterations: its "
                                 f"lowest objective {built.progress.lowest:.6g} stayed above the best fit's "
                                 f"{best_value(abandon_above):.6g} (solver.ABANDON_RULE)")
        infos.append(info)
        budget_hit = stage.final and accept_budget and info.status in BUDGET_STATUSES
        if (stage.final and not budget_hit) or info.status in FATAL_STATUSES:
            check_success(info)
        z = np.asarray(sol["x"]).reshape(-1)
        if warm:
            lam_x = np.asarray(sol["lam_x"]).reshape(-1)
            lam_g = np.asarray(sol["lam_g"]).reshape(-1)
    last = infos[-1]
    return SolveOutcome(z=z, lam_g=lam_g, lam_x=lam_x, status=last.status, success=last.status in SUCCESS_STATUSES,
                        iterations=sum(s.iterations for s in infos), wall_time=sum(s.wall_time for s in infos),
                        objective=last.objective, stages=infos)


def map_in_processes(job, n: int, workers: int) -> list:
    """[job(0), ..., job(n - 1)]: in forked processes where
    tacest.parallel.fork_processes gives more than one for ``workers``, else one after
    another; any exception of a job is raised (independent, seeded computations such as
    the samplers' runs)."""
    processes = fork_processes(workers, n)
    if processes < 2:
        return [job(k) for k in range(n)]
    return fork_map(job, n, processes)


def _restart_reason(last: dict, restart_physics: float) -> str:
    """Why the search goes on after the attempt ``last`` (solve_from_starts' log line)."""
    if last["status"] == "failed":
        return "failed"
    if last["status"] == "abandoned":
        return "was abandoned far above the best"
    if last["status"] == STALLED_STATUS:
        return "stalled (solver.STALL_RULE)"
    if last["status"] in BUDGET_STATUSES:
        return "used up its iteration budget"
    odd = last.get("implausible")
    return " and ".join(
        ([f"violates its own physics by {last['physics_per_sample']:.3g} objective units per sample"]
         if last["physics_per_sample"] > restart_physics else [])
        + ([f"ended at implausible friction ({', '.join(odd)})"] if odd else [])
        + (["misfits its data beyond a local stretch"] if last.get("misfit_local") is False and not odd else [])
    ) or "is not the best fit so far"


def solve_from_starts(starts: list, solve_one, restart_physics: float, attempts: list, min_solves: int = 0,
                      accept_budget: bool = False, workers: int = 1, abandon: bool = False,
                      resume=None, more=None) -> tuple:
    """Solve from each start in turn until a fit is good enough; keep the fit of lowest
    objective (the restarts of the 2-D and 3-D estimators).

    starts : list of (record, start): ``record`` a dict describing the start (copied into
        the attempt's entry), ``start`` what ``solve_one`` takes;
    solve_one(start, abandon_above) -> (SolveOutcome, physics per sample (objective
        units), saved, local, found): one staged solve whose final stage keeps its last
        iterate when it uses up its budget (run_stages' ``accept_budget``) and stops
        where it stays far above ``abandon_above`` (a BestSoFar, or inf: never;
        run_stages' ``abandon_above``, raising StartAbandoned); ``saved`` is whatever the
        caller must restore for that fit; ``local`` whether it may be right: its data
        misfit at most local (fitquality's FitQuality.local) and its friction plausible
        (result.start_verdict; None: not tested); ``found`` a dict of what the fit
        found, copied into its attempt (the ``vertices`` and ``params`` that
        result.basin_spread compares, ``implausible`` where it is); raises
        SolveFailedError when the solve fails;
    restart_physics : a converged fit whose physics per sample is at most this and whose
        misfit of its data is at most local (``local`` not False) ends the search; one
        that violates its physics more, or misfits its data beyond a local stretch, is
        a wrong basin worth another start (a fit of a toppling box whose sampled start
        followed a wrong branch: physics 0.01 per sample, its normals 155 objective
        units off over whole windows, at 2.6 mm where the right basin fits at 15 units);
    attempts : a list that receives one dict per solve (the record with status,
        objective, physics_per_sample, misfit_local and what it found, or status "failed"
        and error), also when every solve fails;
    min_solves : the first this many starts are all solved, whatever their fits (starts
        whose objectives are to be compared: the sampler's);
    accept_budget : fits that used up their budget count as converged ones (the fits
        inside a diagnosis: they may end the search, and are kept when no start
        converged); without it that is a failure, as a single solve's.
    workers : processes that solve the ``min_solves`` compared starts at once, and
        then the restarts in batches of as many (tacest.parallel.fork_processes: 0 one
        per core, 1 one after another).  The batch's fits are taken in order as if
        solved one after another: those after the one that ends the search are
        discarded unseen, so that the kept fit and the attempts (but for those
        ``abandon`` stopped) are the same either way (a restart pair: one solve's time).
    abandon : stop a start whose final stage stays far above the lowest objective of
        the finished fits that count (converged, or any with ``accept_budget``; a
        BestSoFar shared with the starts solved at once; ABANDON_RULE): an attempt of
        status "abandoned".  The kept fit is the same; which starts stop depends on
        which fits end first;
    resume(out, saved) -> what solve_one returns, or None: continues a fit whose final
        stage was stopped as stalled (STALLED_STATUS, :func:`stalled`) from its last
        iterate without that rule.  A stalled fit is set aside, not dropped: it competes
        by its objective and never ends the search; if it is still the fit of lowest
        objective when the search ends, it is resumed and the resumed fit kept (its
        attempt's entry then holds the resumed fit, ``resumed`` true).  Where it is
        resumed it counts as a finished fit for ``abandon``;
    more() -> further (record, start) pairs, or None: restarts made only once the search
        reaches the end of ``starts`` (the 3-D estimator's further push-tracked starts).

    A fit whose final stage used up its iteration budget (BUDGET_STATUSES) competes by
    its objective like a converged one and keeps its status (success False: the caller
    reports it), but never ends the search (the search ends when the converged fit of
    lowest objective is good enough, and the fit of lowest objective is too): a start that creeps along a flat valley
    towards the right basin is worth more than a converged fit of a wrong one (a 3-D
    touch-only fit ended at objective 51.8 after 800 iterations, Chamfer 0.9 mm, the
    converged restart at 75.8, 17.7 mm).

    Returns (out, saved): the kept fit and its ``saved``.  When no start gives a fit (or,
    without ``accept_budget``, no converged one), raises the first start's
    SolveFailedError (a fit that used up its budget is a failure there; ``attempts``
    holds every attempt).
    """
    best = failure = converged = None  # converged: (objective, good) of the best converged fit
    starts = list(starts)
    n_pre = min(int(min_solves), len(starts))
    processes = fork_processes(workers, n_pre)
    solved = {}
    shared = BestSoFar() if abandon else float("inf")

    def solve(k):  # solve start k; its fit, where it counts, is offered to the others
        result = solve_one(starts[k][1], shared)
        status = result[0].status
        if abandon and (status in SUCCESS_STATUSES or accept_budget or (resume and status == STALLED_STATUS)):
            shared.offer(result[0].objective)
        return result

    if processes > 1:
        log.info(f"solving the {n_pre} compared starts in {processes} processes")
        solved = dict(enumerate(fork_map(solve, n_pre, processes, returned=(SolveFailedError,))))
    # ends at a good converged fit once the compared starts are in, unless the kept (budget) fit violates its physics
    for k, record in _in_turn(starts, more, lambda k: k >= min_solves and converged is not None
                              and converged[1] and best[2]):
        _announce(k, min_solves, len(starts), attempts, restart_physics)
        if k and k not in solved:  # a restart: with the next ones in as many processes as may run
            solved.update(_solve_at_once(k, len(starts), workers, solve))
        try:
            result = solved[k] if k in solved else solve(k)
            if isinstance(result, SolveFailedError):
                raise result
            out, physics, saved, local, found = result
        except StartAbandoned as exc:
            log.info(f"start {k + 1}: {exc}")
            attempts.append({**record, "status": "abandoned", "error": str(exc)})
            continue
        except SolveFailedError as exc:
            failure = failure or exc
            attempts.append({**record, "status": "failed", "error": str(exc)})
            continue
        if out.status not in SUCCESS_STATUSES:
            failure = failure or stage_failure(out.stages[-1])
        attempts.append({**record, **_fit_entry(out, physics, local, found)})
        if not np.isfinite(out.objective):
            failure = failure or SolveFailedError(f"IPOPT ended at a non-finite objective ({out.status})")
            continue
        good, converged = _judged(out, physics, local, restart_physics, accept_budget, converged)
        if best is None or out.objective < best[0].objective:
            best = (out, saved, good, len(attempts) - 1)
    if best is not None and resume is not None and best[0].status == STALLED_STATUS:
        best, converged = _resumed(best, converged, resume, attempts, restart_physics, accept_budget)
    if best is None or (converged is None and not accept_budget):
        raise failure
    if best[0].status in BUDGET_STATUSES:
        log.info(f"kept the fit of lowest objective ({best[0].objective:.6g}), whose final stage used up its "
                 f"iteration budget: {best[0].status}")
    return best[0], best[1]


def _in_turn(starts: list, more, stop):
    """(k, record) of each start of :func:`solve_from_starts` in turn until stop(k);
    when ``starts`` are used up, they are extended (in place) by ``more()``, once."""
    k = 0
    while not stop(k):
        if k == len(starts):
            if more is None:
                return
            starts.extend(more())
            more = None
            continue
        yield k, starts[k][0]
        k += 1


def _resumed(best: tuple, converged, resume, attempts: list, restart_physics: float, accept_budget: bool) -> tuple:
    """(best, converged) of :func:`solve_from_starts` after resuming its kept fit, which
    had stalled; its attempt's entry is replaced by the resumed fit's."""
    out, saved, _, index = best
    log.info(f"resuming the stalled fit of lowest objective ({out.objective:.6g}) from its last iterate")
    try:
        out, physics, saved, local, found = resume(out, saved)
    except SolveFailedError as exc:  # the stalled fit stays what it was: a budget fit
        attempts[index]["resume_error"] = str(exc)
        return best, converged
    if not np.isfinite(out.objective):  # kept as it was, and the entry says why
        attempts[index]["resume_error"] = f"the resumed fit ended at objective {out.objective} ({out.status})"
        return best, converged
    good, converged = _judged(out, physics, local, restart_physics, accept_budget, converged)
    attempts[index].update({**_fit_entry(out, physics, local, found), "resumed": True})
    return (out, saved, good, index), converged


def _fit_entry(out, physics, local, found) -> dict:
    """A finished fit's fields of its attempt entry (:func:`solve_from_starts`)."""
    return {"status": out.status, "objective": float(out.objective), "physics_per_sample": float(physics),
            "misfit_local": local, **found}


def _judged(out, physics, local, restart_physics, accept_budget, converged) -> tuple:
    """(good, converged) of :func:`solve_from_starts` after a finished fit: whether it
    holds its physics and misfits its data at most locally, and the (objective, good)
    of the converged fit of lowest objective (budget fits count with accept_budget)."""
    good = bool(physics <= restart_physics and local is not False)
    if (out.status in SUCCESS_STATUSES or accept_budget) and (converged is None or out.objective < converged[0]):
        converged = (out.objective, good)
    return good, converged


def _announce(k: int, min_solves: int, n: int, attempts: list, restart_physics: float):
    """The log line before start k of :func:`solve_from_starts` (none before the first)."""
    if 0 < k < min_solves:
        log.info(f"start {k + 1} of the {min_solves} compared")
    elif k:
        log.info(f"restart {k}/{n - 1} from another start: the last fit "
                 f"{_restart_reason(attempts[-1], restart_physics)}")


def _solve_at_once(k: int, n: int, workers: int, solve) -> dict:
    """{start index: solve(index)} of the restarts from k on (of n starts) that run at
    once in forked processes (tacest.parallel.fork_map; failures returned), or {} where
    only one process may run (they are then solved one at a time)."""
    batch = list(range(k, n))
    processes = fork_processes(workers, len(batch))
    if processes < 2:
        return {}
    batch = batch[:processes]
    return dict(zip(batch, fork_map(lambda j: solve(batch[j]), len(batch), processes, returned=(SolveFailedError,))))


def attempts_json(attempts: list) -> str:
    """JSON text of the attempt dicts of :func:`solve_from_starts` (arrays as lists):
    the estimate's attr ``starts``."""
    return json.dumps([{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in a.items()}
                       for a in attempts])
