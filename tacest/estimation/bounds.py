"""Hard bounds of the physical parameters (scaled units), shared by every estimator."""

from __future__ import annotations

import numpy as np

#: log(m / m0): a factor e^6 either way of the mass scale
LOG_MASS_BOUNDS = (-6.0, 6.0)
#: friction coefficients
FRICTION_BOUNDS = (0.01, 2.0)
#: 2-D log(I / I_uniform): below, a ring-like mass distribution; ln 2 keeps
#: I <= m · r_max² for any convex shape (physically valid)
LOG_INERTIA_BOUNDS = (-1.5, float(np.log(2.0)))
#: 3-D log-Cholesky diagonal of I / (m L²): sqrt of the second moment per unit mass
#: between e^-8 L and e^2 L (any object of size ~L lies far inside); off-diagonals ±2 L
INERTIA_DIAG_BOUNDS = (-8.0, 2.0)
INERTIA_OFFDIAG_BOUND = 2.0
