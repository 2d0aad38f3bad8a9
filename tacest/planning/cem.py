"""Cross-entropy method (CEM) for maximizing a black-box score over a box of R^d.

Iteration 0 spreads its population evenly over the box (stratified: one uniform draw in
each of ``population`` equal slices of the first coordinate, the others uniform), so a
multi-modal score (pokes from the left and from the right) is seen before the
Gaussian narrows down.  Each later iteration draws from a diagonal Gaussian fitted to
the elite (best ``elite`` samples so far), clipped to the box, with the standard
deviation kept above ``min_std`` × the box width so that it does not collapse early.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CEMResult:
    """Every evaluated point and its score (N, d), (N,); best : index of the maximum."""

    samples: np.ndarray
    scores: np.ndarray

    @property
    def best(self) -> int:
        return int(np.nanargmax(self.scores))


def cem_maximize(fun, lo, hi, rng: np.random.Generator, iterations: int = 4, population: int = 12,
                 elite: int = 4, min_std: float = 0.03, smoothing: float = 0.8, many=None) -> CEMResult:
    """Maximize ``fun(x) -> float`` over lo <= x <= hi (arrays of d) with CEM.

    iterations × population evaluations in all.  ``smoothing`` weights the new
    elite statistics against the previous ones (1: no memory).  A NaN score counts as
    the worst.  ``many(X) -> (n,)`` scores the rows of one iteration's X (n, d) at once
    in place of ``fun`` row by row (e.g. in parallel; it must give what ``fun`` gives).
    """
    lo = np.asarray(lo, float).reshape(-1)
    hi = np.asarray(hi, float).reshape(-1)
    d = lo.shape[0]
    width = hi - lo
    xs, ys = [], []
    X = lo + rng.random((population, d)) * width
    X[:, 0] = lo[0] + (np.arange(population) + rng.random(population)) / population * width[0]
    mean = std = None
    for it in range(iterations):
        if it > 0:
            X = np.clip(mean + std * rng.standard_normal((population, d)), lo, hi)
        Y = [fun(x) for x in X] if many is None else many(X)
        for x, y in zip(X, Y):
            xs.append(x.copy())
            y = float(y)
            ys.append(y if np.isfinite(y) else -np.inf)
        order = np.argsort(-np.asarray(ys))[:elite]
        E = np.asarray(xs)[order]
        m_new, s_new = E.mean(0), np.maximum(E.std(0), min_std * width)
        if mean is None:
            mean, std = m_new, np.maximum(s_new, 0.25 * width)
        else:
            mean = smoothing * m_new + (1 - smoothing) * mean
            std = smoothing * s_new + (1 - smoothing) * std
    return CEMResult(samples=np.asarray(xs).reshape(-1, d), scores=np.asarray(ys))
