"""Solving the NLP with IPOPT: build once per structure, homotopy, warm starts, honest status."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from tacest.errors import SolveFailedError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.problem import Problem2D, RunStructure
from tacest.interrupt import raise_if_interrupted, watch_interrupts

#: IPOPT statuses that count as a solution
SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: statuses after which not even an intermediate iterate can be used
FATAL_STATUSES = ("Invalid_Number_Detected", "Error_In_Step_Computation", "Insufficient_Memory",
                  "Internal_Error", "Invalid_Problem_Definition", "Invalid_Option", "Unrecoverable_Exception",
                  "NonIpopt_Exception_Thrown")

_CACHE: dict = {}


@dataclass
class StageInfo:
    name: str
    status: str
    iterations: int
    wall_time: float
    objective: float


@dataclass
class SolveOutcome:
    """What IPOPT returned over all homotopy stages."""

    z: np.ndarray
    lam_g: np.ndarray
    lam_x: np.ndarray
    status: str
    success: bool
    iterations: int
    wall_time: float
    objective: float
    stages: list = field(default_factory=list)


class _Progress(ca.Callback):
    """IPOPT iteration callback: one progress line every ``every`` iterations."""

    def __init__(self, nx, ng, lbg, ubg, every):
        ca.Callback.__init__(self)
        self.nx, self.ng = nx, ng
        self.lbg, self.ubg = lbg, ubg
        self.every = max(1, int(every))
        self.echo = None
        self.label = ""
        self.it = 0
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
        if self.echo is not None and self.it % self.every == 0:
            g = np.asarray(arg[ca.nlpsol_out().index("g")]).reshape(-1)
            inf = float(np.max(np.concatenate([[0.0], self.lbg - g, g - self.ubg]))) if g.size else 0.0
            f = float(arg[ca.nlpsol_out().index("f")])
            self.echo(f"  {self.label} iter {self.it:4d}  objective {f:12.5e}  infeasibility {inf:9.2e}")
        self.it += 1
        return [0]


class BuiltSolver:
    """A Problem2D and its IPOPT solver, built once per (shape, structures, options)."""

    def __init__(self, problem: Problem2D, config: EstimatorConfig):
        self.problem = problem
        sc = config.solver
        self.progress = _Progress(problem.n_z, problem.g.shape[0], problem.lbg, problem.ubg, sc.print_every)
        self.config = config
        self.solvers = {}

    def _make(self, problem, config, mode, max_iter=None):
        sc = config.solver
        opts = {
            "expand": False,
            "hess_lag": problem.hess_lag[mode],
            "print_time": False,
            "iteration_callback": self.progress,
            "ipopt": {
                "print_level": 0,
                "sb": "yes",
                "linear_solver": sc.linear_solver,
                "tol": sc.tol,
                "acceptable_tol": sc.acceptable_tol,
                "acceptable_iter": 5,
                # An acceptable point: constraints (kinematics in object lengths per
                # second, lifted parameters relative) met to 1e-4, and the objective, a
                # chi-square sum of thousands of whitened residuals, changing by less than
                # 1e-3 of itself per iteration for acceptable_iter iterations.  The last
                # iterations mostly slide along the weakly determined mass–friction
                # valley (only mu·m·g is seen in steady sliding), which the information
                # matrix reports; shape and trajectory have long settled by then.
                "acceptable_constr_viol_tol": 1e-4,
                # Complementarity of the bounds (lambda_n >= 0) is x_i z_i in objective
                # units (unscaled: half a chi-square): with the monotone barrier held at
                # mu_init it stays near mu / (IPOPT's objective scaling, ~1e-3..1e-2),
                # ~3e-3.  0.1 of an objective unit is far below what the data resolve
                # (one whitened residual of 0.45 sigma); 1e-3 kept converged fits
                # iterating to the iteration limit.
                "acceptable_compl_inf_tol": 0.1,
                "acceptable_obj_change_tol": 1e-3,
                "max_iter": sc.max_iter if max_iter is None else max_iter,
                "max_cpu_time": sc.max_cpu_time,
                # every stage starts from a consistent point (see estimator.solve): a small
                # barrier parameter and bound push keep IPOPT from pushing contact impulses
                # off their bounds into the interior
                "mu_strategy": "monotone",
                "mu_init": 1e-5,
                "bound_push": 1e-8,
                "bound_frac": 1e-8,
                "warm_start_init_point": "yes",
                "warm_start_bound_push": 1e-8,
                "warm_start_bound_frac": 1e-8,
                "warm_start_mult_bound_push": 1e-8,
            },
        }
        # a problem may supply its own derivative functions (grad_f, jac_g) and IPOPT options
        extra = dict(getattr(problem, "nlpsol_options", None) or {})
        opts["ipopt"].update(extra.pop("ipopt", {}))
        opts.update(extra)
        return ca.nlpsol(f"tacest_nlp_{mode.replace('-', '_')}", "ipopt", problem.nlp, opts)

    def solve(self, z0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None, label="", echo=None,
              hessian="gauss-newton", max_iter=None):
        """One IPOPT solve with the given Hessian model; returns (solution dict, StageInfo)."""
        key = (hessian, max_iter)
        if key not in self.solvers:
            self.solvers[key] = self._make(self.problem, self.config, hessian, max_iter)
        solver = self.solvers[key]
        self.progress.echo = echo
        self.progress.label = label
        self.progress.lbg, self.progress.ubg = lbg, ubg
        self.progress.it = 0
        args = dict(x0=z0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        if lam_x0 is not None:
            args["lam_x0"] = lam_x0
        if lam_g0 is not None:
            args["lam_g0"] = lam_g0
        t0 = time.perf_counter()
        with watch_interrupts() as watch:
            sol = solver(**args)
        wall = time.perf_counter() - t0
        st = solver.stats()
        raise_if_interrupted(st.get("return_status", "unknown"), watch)
        return sol, StageInfo(name=label, status=st.get("return_status", "unknown"),
                              iterations=int(st.get("iter_count", 0)), wall_time=wall,
                              objective=float(sol["f"]))


def get_solver(shape, structures: list[RunStructure], config: EstimatorConfig, effects=()) -> BuiltSolver:
    """The cached solver for this structure and model (built on first use); effects:
    the NLP augmentations (problem.NLP_EFFECTS) included as extra parameters."""
    from tacest.estimation.problem import check_effects

    effects = check_effects(effects)
    key = (shape.name, tuple(structures), repr(config.solver), config.weights.occam > 0,
           config.noise.complementarity_reach > 0) + ((effects,) if effects else ())
    if key not in _CACHE:
        _CACHE[key] = BuiltSolver(Problem2D(shape, structures, config, effects=effects), config)
    return _CACHE[key]


def check_success(info: StageInfo):
    if info.status not in SUCCESS_STATUSES:
        raise SolveFailedError(f"IPOPT failed in stage {info.name!r}: {info.status} after {info.iterations} "
                               "iterations (no estimate written)")


def solve_from_starts(starts: list, solve_one, restart_physics: float, echo, attempts: list) -> tuple:
    """Solve from each start in turn until a fit is physically consistent; keep the
    successful fit of lowest objective (the restarts of the 2-D and 3-D estimators).

    starts : list of (record, start): ``record`` a dict describing the start (copied into
        the attempt's entry), ``start`` what ``solve_one`` takes;
    solve_one(start) -> (SolveOutcome, physics per sample (objective units), saved):
        one staged solve; ``saved`` is whatever the caller must restore for that fit;
        raises SolveFailedError when the solve fails;
    restart_physics : a fit whose physics per sample is at most this ends the search;
    attempts : a list that receives one dict per solve (the record with status,
        objective and physics_per_sample, or status "failed" and error), also when every
        solve fails.

    Returns (out, saved): the kept fit and its ``saved``.  When no start gives a fit,
    raises the first start's SolveFailedError (``attempts`` holds every failure).
    """
    best = failure = None
    for k, (record, start) in enumerate(starts):
        if k:
            last = attempts[-1]
            echo(f"restart {k}/{len(starts) - 1} from another start: the last fit "
                 + ("failed" if last["status"] == "failed" else
                    f"violates its own physics by {last['physics_per_sample']:.3g} objective units per sample"))
        try:
            out, physics, saved = solve_one(start)
        except SolveFailedError as exc:
            failure = failure or exc
            attempts.append({**record, "status": "failed", "error": str(exc)})
            continue
        attempts.append({**record, "status": out.status, "objective": float(out.objective),
                         "physics_per_sample": float(physics)})
        if best is None or out.objective < best[0].objective:
            best = (out, saved)
        if physics <= restart_physics:
            break
    if best is None:
        raise failure
    return best


def attempts_json(attempts: list) -> str:
    """JSON text of the attempt dicts of :func:`solve_from_starts` (arrays as lists):
    the estimate's attr ``starts``."""
    return json.dumps([{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in a.items()}
                       for a in attempts])
