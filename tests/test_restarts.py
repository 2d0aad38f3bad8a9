"""When the estimators' search over starts ends (tacest.estimation.solver.solve_from_starts):
at the first converged fit that holds its own physics (at most ``restart_physics``
objective units per sample) and whose data misfit is at most local (the goodness-of-fit
test's ``local``; None: not tested).  A fit that misfits its data beyond a local stretch
is a wrong basin worth another start however well it holds its physics (a toppling box
whose sampled start stayed flat: physics 0.01 per sample, its normals off over whole
windows), and one that violates its physics is, however local its misfit."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.solver import SolveOutcome, StageInfo, solve_from_starts

RESTART_PHYSICS = 0.1


def _outcome(obj, status="Solve_Succeeded", iterations=3):
    """A one-stage SolveOutcome ending at objective ``obj`` with ``status``."""
    stage = StageInfo(name="homotopy 1/1", status=status, iterations=iterations, wall_time=0.0, objective=obj)
    return SolveOutcome(z=np.full(2, obj), lam_g=np.zeros(0), lam_x=None, status=status,
                        success=status == "Solve_Succeeded", iterations=iterations, wall_time=0.0, objective=obj,
                        stages=[stage])


def _solve(start, abandon_above=float("inf")):
    """start = (objective, physics per sample, local) -> what solve_from_starts takes
    (abandon_above: not used here, see _solve_abandoning)."""
    obj, phys, local = start
    return _outcome(obj), phys, ("saved", obj), local, {}


def _search(fits):
    attempts = []
    out, _ = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate(fits)], _solve, RESTART_PHYSICS,
                               attempts)
    return out.objective, len(attempts)


@pytest.mark.parametrize("first, solved", [
    ((50.0, 0.01, True), 1),   # holds its physics, local misfit: good, the search ends
    ((50.0, 0.01, None), 1),   # holds its physics, not tested: good
    ((50.0, 0.01, False), 3),  # holds its physics but misfits its data widely: restart
    ((50.0, 0.5, True), 3),    # misfit local but its physics violated: restart
    ((50.0, 0.5, None), 3),
])
def test_the_search_goes_on_from_a_fit_that_fails_either_check(first, solved):
    obj, n = _search([first, (60.0, 0.5, False), (40.0, 0.01, True), (10.0, 0.01, True)])
    assert n == solved
    # the kept fit is the lowest objective among those solved
    assert obj == (50.0 if solved == 1 else 40.0)


# ---------------------------------------------------------------------------------------
# hopeless restarts stopped early (solver.ABANDON_RULE, solver.hopeless)

def test_the_rule_stops_only_after_its_iterations_and_only_far_above_the_best():
    from tacest.estimation.solver import hopeless

    assert not hopeless(19, 1e9, 1.0)  # never before 20 iterations
    assert hopeless(20, 10.1, 1.0) and not hopeless(20, 9.9, 1.0)
    assert hopeless(30, 5.1, 1.0) and not hopeless(29, 5.1, 1.0)
    assert hopeless(100, 3.1, 1.0) and not hopeless(400, 2.9, 1.0)
    for best in (float("inf"), float("nan"), 0.0, -1.0):  # no best fit yet, or one it cannot scale
        assert not hopeless(1000, 1e12, best)


def _solve_abandoning(start, abandon_above=float("inf")):
    """As _solve, but a start whose objective is above 10x abandon_above is abandoned
    (what run_stages does when its final stage is hopeless); the thresholds it saw are
    recorded."""
    from tacest.estimation.solver import StartAbandoned

    from tacest.estimation.solver import best_value

    SEEN.append(best_value(abandon_above))
    if start[0] > 10 * best_value(abandon_above):
        raise StartAbandoned(f"abandoned: {start[0]} above {best_value(abandon_above)}")
    return _solve(start)


SEEN: list = []


@pytest.mark.parametrize("abandon", [True, False])
def test_a_hopeless_start_is_recorded_as_abandoned_and_the_best_fit_kept(abandon):
    SEEN.clear()
    # two compared starts, then restarts: 800 and 900 are far above the first fit's 50
    # (abandoned when allowed, the compared one too), 45 is kept
    fits = [(50.0, 0.5, True), (800.0, 0.5, True), (900.0, 0.5, True), (45.0, 0.01, True)]
    attempts = []
    out, saved = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate(fits)], _solve_abandoning,
                                   RESTART_PHYSICS, attempts, min_solves=2, abandon=abandon)
    assert out.objective == 45.0 and saved == ("saved", 45.0)
    assert [a["status"] for a in attempts] == (["Solve_Succeeded", "abandoned", "abandoned", "Solve_Succeeded"]
                                               if abandon else ["Solve_Succeeded"] * 4)
    # the first start sees no threshold; each later one the lowest objective before it
    assert SEEN == ([float("inf"), 50.0, 50.0, 50.0] if abandon else [float("inf")] * 4)


@pytest.mark.parametrize("second", ["abandoned", "failed"])
def test_a_compared_start_that_stops_far_above_a_good_fit_starts_no_restart(second):
    """The search ends once the compared starts are in and the best is good, whatever
    became of the last compared start: an abandoned one (far above the best) or a
    failed one is no reason to restart (the restarts used to run there, and every one
    was then abandoned: 20 s for a fit of 6 s on a gentle box)."""
    from tacest.errors import SolveFailedError

    def solve(start, abandon_above=float("inf")):
        if start == "second":
            if second == "failed":
                raise SolveFailedError("IPOPT: Restoration_Failed")
            return _solve_abandoning((900.0, 0.01, True), abandon_above)
        return _solve(start)

    fits = [(50.0, 0.01, True), "second", (40.0, 0.01, True)]
    attempts = []
    out, _ = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate(fits)], solve, RESTART_PHYSICS,
                               attempts, min_solves=2, abandon=True)
    assert out.objective == 50.0
    assert [a["status"] for a in attempts] == ["Solve_Succeeded", second]
    # a bad first fit still starts the restarts after the same compared start
    attempts = []
    out, _ = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate([(50.0, 0.5, True)] + fits[1:])],
                               solve, RESTART_PHYSICS, attempts, min_solves=2, abandon=True)
    assert out.objective == 40.0 and len(attempts) == 3


def test_a_fit_that_used_up_its_budget_stops_no_start_unless_budget_fits_count():
    """Without accept_budget a fit that used up its budget cannot end the search alone
    (no converged fit: a failure); so it must not stop the converged start after it."""
    from tacest.estimation.solver import StartAbandoned, best_value

    def solve(start, abandon_above=float("inf")):
        obj, status = start
        if obj > 10 * best_value(abandon_above):
            raise StartAbandoned("abandoned")
        out, *rest = _solve((obj, 0.01, True))
        out.status = status
        return (out, *rest)

    fits = [(50.0, "Maximum_Iterations_Exceeded"), (900.0, "Solve_Succeeded")]
    for accept_budget, statuses in ((False, ["Maximum_Iterations_Exceeded", "Solve_Succeeded"]),
                                    (True, ["Maximum_Iterations_Exceeded", "abandoned"])):
        attempts = []
        out, _ = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate(fits)], solve, RESTART_PHYSICS,
                                   attempts, min_solves=2, abandon=True, accept_budget=accept_budget)
        assert [a["status"] for a in attempts] == statuses and out.objective == 50.0


def _rosenbrock_solver():
    """A BuiltSolver on 100 + Rosenbrock(x) (exact Hessian): from (-5, 10) IPOPT takes
    31 iterations to its minimum 100; from (-1.2, 1) 18."""
    import types

    import casadi as ca

    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.solver import BuiltSolver

    x, p, lam_f = ca.SX.sym("x", 2), ca.SX.sym("p", 0), ca.SX.sym("lam_f")
    f = 100 + (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2
    hess = ca.Function("h", [x, p, lam_f, ca.SX.sym("lam_g", 0)], [ca.triu(lam_f * ca.hessian(f, x)[0])])
    problem = types.SimpleNamespace(nlp={"x": x, "p": p, "f": f, "g": ca.SX(0, 1)}, lbg=np.zeros(0),
                                    ubg=np.zeros(0), n_z=2, g=ca.SX(0, 1), hess_lag={"exact": hess})
    return BuiltSolver(problem, EstimatorConfig())


def test_ipopt_is_stopped_at_the_rules_iteration_and_not_taken_for_a_ctrl_c():
    from tacest.estimation.solver import ABANDONED_STATUS, SUCCESS_STATUSES

    built = _rosenbrock_solver()
    free = -np.inf * np.ones(2), np.inf * np.ones(2)
    _, whole = built.solve(np.array([-5.0, 10.0]), np.zeros(0), *free, hessian="exact")
    assert whole.status in SUCCESS_STATUSES and whole.iterations > 20
    # its objective never falls below 100: beside a best fit of 1 it is hopeless at 20
    _, info = built.solve(np.array([-5.0, 10.0]), np.zeros(0), *free, hessian="exact", abandon_above=1.0)
    assert info.status == ABANDONED_STATUS and info.iterations == 20
    # beside a best fit of 50 (the rule needs 500 at 20, 250 at 30, 150 at 100) it runs on
    _, info = built.solve(np.array([-5.0, 10.0]), np.zeros(0), *free, hessian="exact", abandon_above=50.0)
    assert info.status in SUCCESS_STATUSES and info.iterations == whole.iterations
    # the next solve without a threshold is not stopped (the threshold does not stick)
    _, info = built.solve(np.array([-5.0, 10.0]), np.zeros(0), *free, hessian="exact")
    assert info.status in SUCCESS_STATUSES


def test_run_stages_raises_start_abandoned_only_from_the_final_stage():
    from tacest.estimation.solver import Stage, StartAbandoned, run_stages

    built = _rosenbrock_solver()
    free = -np.inf * np.ones(2), np.inf * np.ones(2)
    stages = [Stage(label, 1.0, 1.0, 1.0, impulses_only=False, hessian="exact", max_iter=400, final=final)
              for label, final in (("first", False), ("last", True))]
    bounds = lambda stage, z: (free[0].copy(), free[1].copy())  # noqa: E731
    params = lambda stage, retry=False: np.zeros(0)  # noqa: E731
    # the first stage (not final) runs to its end beside any threshold; the final stage
    # starts at its minimum and ends at once, below 10x 11
    out = run_stages(built, np.array([-5.0, 10.0]), stages, params, bounds, abandon_above=11.0)
    assert out.success and out.stages[0].iterations > 20
    with pytest.raises(StartAbandoned, match="abandoned in stage 'last' after 20 iterations"):
        run_stages(built, np.array([-5.0, 10.0]), stages[1:], params, bounds, abandon_above=1.0)


def test_a_stalled_final_stage_is_stopped_and_kept_only_where_budget_fits_are(monkeypatch):
    """The stall rule (solver.STALL_RULE) on the Rosenbrock problem: with a rule that any
    stage meets (a gain of 1000 % of the objective over 3 iterations, from iteration 5)
    a final stage that keeps budget fits stops at iteration 5 with STALLED_STATUS and its
    last iterate, which counts as a budget fit (not a success); without accept_budget,
    or in a stage that is not final, the rule does not act and the stage converges."""
    import tacest.estimation.solver as S

    built = _rosenbrock_solver()
    free = -np.inf * np.ones(2), np.inf * np.ones(2)
    bounds = lambda stage, z: (free[0].copy(), free[1].copy())  # noqa: E731
    params = lambda stage, retry=False: np.zeros(0)  # noqa: E731
    first, last = [S.Stage(label, 1.0, 1.0, 1.0, impulses_only=False, hessian="exact", max_iter=400, final=final)
                   for label, final in (("first", False), ("last", True))]
    z0 = np.array([-5.0, 10.0])
    whole = S.run_stages(built, z0, [last], params, bounds, accept_budget=True, stop_stalled=True)
    assert whole.success and whole.iterations > 20  # the real rule: no stall in a converging solve
    monkeypatch.setattr(S, "STALL_RULE", (5, 3, 10.0))
    out = S.run_stages(built, z0, [last], params, bounds, accept_budget=True, stop_stalled=True)
    assert out.status == S.STALLED_STATUS and out.status in S.BUDGET_STATUSES and not out.success
    assert out.iterations == 5 and np.all(np.isfinite(out.z)) and not np.allclose(out.z, z0)
    assert S._restart_reason({"status": out.status, "physics_per_sample": 0.0}, 0.1).startswith("stalled")
    for kwargs in ({"accept_budget": False, "stop_stalled": True}, {"accept_budget": True, "stop_stalled": False}):
        out = S.run_stages(built, z0, [last], params, bounds, **kwargs)
        assert out.success and out.iterations == whole.iterations, kwargs
    out = S.run_stages(built, z0, [first, last], params, bounds, accept_budget=True, stop_stalled=True)
    assert out.stages[0].status in S.SUCCESS_STATUSES and out.stages[0].iterations == whole.iterations
    assert out.stages[1].status == S.STALLED_STATUS  # the final stage, at the minimum, stalls there


def test_the_stall_rule_reads_the_lowest_objective_over_its_window():
    from tacest.estimation.solver import STALL_RULE, stalled

    start, window, gain = STALL_RULE
    flat = [100.0] * (start + 1)
    assert stalled(flat) and not stalled(flat[:-1])  # not before iteration `start`
    falling = list(100.0 * (1.0 - 2 * gain / window) ** np.arange(start + 1))  # ~2 % per window
    assert not stalled(falling)
    assert not stalled([np.inf] * (start - window + 1) + [5.0] * window)  # no finite value a window ago


def _solve_status(start, abandon_above=float("inf")):
    """start = (objective, status) -> a fit with that final status, physics 0.01, local."""
    obj, status = start
    return _outcome(obj, status, iterations=150), 0.01, ("saved", obj), True, {}


@pytest.mark.parametrize("resumed_to", ["Solve_Succeeded", "Maximum_Iterations_Exceeded", "failed", "nan"])
def test_a_stalled_fit_is_set_aside_and_resumed_only_if_it_is_kept(resumed_to):
    """A stalled fit (solver.STALLED_STATUS) never ends the search; kept at its end (the
    lowest objective), it is resumed from its last iterate and the resumed fit replaces
    it (attempt marked resumed); one that a converged fit beats is not resumed.  Without
    a resume it is kept as the budget fit it is, and alone it is a failure."""
    from tacest.errors import SolveFailedError
    from tacest.estimation.solver import STALLED_STATUS

    calls = []

    def resume(out, saved):
        calls.append((out.objective, saved))
        if resumed_to == "failed":
            raise SolveFailedError("IPOPT failed in stage 'homotopy 1/1' (resumed)")
        if resumed_to == "nan":  # a resume that ends at a non-finite objective is no fit
            return _solve_status((float("nan"), "Maximum_Iterations_Exceeded"))
        return _solve_status((out.objective - 1.0, resumed_to))

    def search(fits, **kw):
        attempts = []
        out, saved = solve_from_starts([({"start": f"s{k}"}, f) for k, f in enumerate(fits)], _solve_status,
                                       RESTART_PHYSICS, attempts, **kw)
        return out, saved, attempts

    # stalled at 10, then a good converged fit at 20 ends the search; 10 is kept and resumed
    out, saved, attempts = search([(10.0, STALLED_STATUS), (20.0, "Solve_Succeeded"), (5.0, "Solve_Succeeded")],
                                  resume=resume)
    assert len(attempts) == 2 and calls == [(10.0, ("saved", 10.0))]
    if resumed_to in ("failed", "nan"):
        assert out.status == STALLED_STATUS and out.objective == 10.0 and "resume_error" in attempts[0]
        assert "resumed" not in attempts[0] and attempts[0]["objective"] == 10.0
    else:
        assert out.status == resumed_to and out.objective == 9.0 and saved == ("saved", 9.0)
        assert attempts[0]["resumed"] and attempts[0]["status"] == resumed_to and attempts[0]["objective"] == 9.0
    # beaten by a converged fit: not resumed
    calls.clear()
    out, _, _ = search([(30.0, STALLED_STATUS), (20.0, "Solve_Succeeded")], resume=resume)
    assert out.objective == 20.0 and calls == []
    # no resume: the stalled fit is a budget fit; kept beside a converged one, alone a failure
    out, _, _ = search([(10.0, STALLED_STATUS), (20.0, "Solve_Succeeded")])
    assert out.status == STALLED_STATUS
    with pytest.raises(SolveFailedError):
        search([(10.0, STALLED_STATUS)])
    # alone, with a resume: a converged resumed fit is an estimate, a failed resume is not
    if resumed_to == "Solve_Succeeded":
        assert search([(10.0, STALLED_STATUS)], resume=resume)[0].objective == 9.0
    else:
        with pytest.raises(SolveFailedError):
            search([(10.0, STALLED_STATUS)], resume=resume)


def test_the_solver_cache_keeps_the_most_recently_used_structures_only():
    """SolverCache holds at most ``limit`` built solvers and drops the least recently
    used first: a structure used again survives the next build, the oldest unused one
    does not (an unbounded cache held every structure of a process's life: 5.3 GB
    after one diagnosis, and a closed loop of diagnoses was killed for memory)."""
    from tacest.estimation.solver import SolverCache

    builds = []

    def build(key):
        return lambda: builds.append(key) or f"solver {key}"

    cache = SolverCache(limit=2)
    assert cache.get("a", build("a")) == "solver a"
    cache.get("b", build("b"))
    cache.get("a", build("a"))  # used again: now the most recent
    cache.get("c", build("c"))  # drops b, the least recently used
    assert len(cache) == 2 and builds == ["a", "b", "c"]
    cache.get("a", build("a"))
    assert builds == ["a", "b", "c"]  # a was kept
    cache.get("b", build("b"))
    assert builds == ["a", "b", "c", "b"]  # b was not
    with pytest.raises(ValueError):
        SolverCache(limit=0)
