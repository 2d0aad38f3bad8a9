"""Physical constants and shared numerical tolerances: the one home of each.

A value that two modules must agree on lives here; a tolerance that belongs to one
law lives beside that law, with its reason (e.g. ``tacest.dynamics.laws``).
"""

from __future__ import annotations

#: m/s², standard gravity (ISO 80000-3).  What tacest's simulators use, what a recorder
#: writes into a run's ``gravity`` attr when it knows nothing better, and the unit of
#: force in the scaled problems (m0·g, see ``tacest.estimation.data.Scales``).  The
#: estimators take the magnitude of each run's own ``gravity`` (SPEC) for the physics;
#: this constant only sets the scale of forces and impulses.
STANDARD_GRAVITY = 9.81
