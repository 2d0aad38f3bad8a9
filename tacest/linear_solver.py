"""Is IPOPT's linear solver there?  Checked before any work, not after it.

IPOPT loads the HSL solvers (ma27, ma57, ma86, ma97) from a separate shared library at
the first solve; without it every solve returns ``Invalid_Option`` with an iteration
count that was never set ("Invalid_Option after -554753936 iterations").  The commands
that solve call :func:`check_linear_solver` on their configuration first: one tiny NLP
with the solver asked for, which either solves or names what is missing.
"""

from __future__ import annotations

from tacest.errors import TacestError

#: the linear solver bundled with CasADi's IPOPT: always there
BUNDLED = "mumps"
#: solvers from the HSL library, which IPOPT loads at run time
HSL_SOLVERS = ("ma27", "ma57", "ma86", "ma97")

_checked: dict = {}


def check_linear_solver(name: str) -> None:
    """TacestError unless IPOPT can use the linear solver ``name`` (cached per process)."""
    if name == BUNDLED:
        return
    if name not in _checked:
        import casadi as ca

        x = ca.SX.sym("x")
        probe = ca.nlpsol("tacest_linear_solver_probe", "ipopt", {"x": x, "f": (x - 1) ** 2},
                          {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "linear_solver": name}})
        probe(x0=0.0)
        _checked[name] = probe.stats().get("return_status", "unknown")
    status = _checked[name]
    if status in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
        return
    if name in HSL_SOLVERS:
        need = "the HSL library (libhsl.so or libcoinhsl.so, installed separately, on the library path)"
    else:
        need = f"an IPOPT built with {name}"
    raise TacestError(f"solver.linear_solver = {name!r}: IPOPT cannot use it ({status}); it needs {need}, "
                      f"or set linear_solver = \"{BUNDLED}\"")
