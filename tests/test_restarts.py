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


def _solve(start):
    """start = (objective, physics per sample, local) -> what solve_from_starts takes."""
    obj, phys, local = start
    stage = StageInfo(name="homotopy 1/1", status="Solve_Succeeded", iterations=3, wall_time=0.0, objective=obj)
    out = SolveOutcome(z=np.full(2, obj), lam_g=np.zeros(0), lam_x=None, status="Solve_Succeeded", success=True,
                       iterations=3, wall_time=0.0, objective=obj, stages=[stage])
    return out, phys, ("saved", obj), local, {}


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
