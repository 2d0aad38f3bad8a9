"""Scalar scores of a candidate's expected information F against the past information.

I_past (n, n) is what the data so far (and the estimator's prior) say about the
parameters and the current pose: the posterior information I_obs + I_prior
(tacest.information.expected.past_information).  F (n, n) is the expected information of
the candidate.  Larger scores are better; every score is 0 for F = 0 (a poke that adds
nothing) except ``D``, which is the absolute criterion.

- ``logdet`` (the default): log det(F I_past⁻¹ + I) = Σ log(1 + μ_i), μ the eigenvalues
  of I_past^{-1/2} F I_past^{-1/2}.  Twice the expected information gain (nats) of a
  linear-Gaussian model; invariant to the units and parameterization of the rows.  A
  direction the past data already pin down (large I_past) discounts F there.
- ``D``: the classical D-criterion of the posterior after the poke, log det(Ĩ_past + F̃)
  in coordinates scaled by the current standard deviations (tilde, see below).  It
  differs from ``logdet`` by log det Ĩ_past, which does not depend on the candidate, so
  it ranks candidates exactly as ``logdet`` does.
- ``A``: the A-criterion as a gain: Σ_i (1 − C_post,ii / C_past,ii), the summed
  fractional reduction of each parameter's variance (C = I⁻¹); in [0, n].
- ``E``: the E-criterion as a gain: log λ_min(Ĩ_past + F̃) − log λ_min(Ĩ_past), how much
  the worst-determined direction improves.

Scaled coordinates (A, D, E): θ̃_i = θ_i / σ_i with σ_i = sqrt(C_past,ii) the current
standard deviation, so that lengths, masses and angles are comparable (the classical
A and E criteria depend on the units of the rows).
"""

from __future__ import annotations

import numpy as np

from tacest.errors import TacestError

SCORES = ("logdet", "A", "D", "E")


def _chol(I_past):
    try:
        return np.linalg.cholesky(I_past)
    except np.linalg.LinAlgError:
        raise TacestError("the past information matrix is not positive definite "
                          "(the estimate's /information/observed is broken?)") from None


def whitened(F: np.ndarray, I_past: np.ndarray) -> np.ndarray:
    """M = C⁻¹ F C⁻ᵀ with I_past = C Cᵀ (Cholesky): F in the metric of the past."""
    C = _chol(I_past)
    X = np.linalg.solve(C, F)
    M = np.linalg.solve(C, X.T).T
    return 0.5 * (M + M.T)


def score(F: np.ndarray, I_past: np.ndarray, kind: str = "logdet") -> float:
    """The ``kind`` score (module docstring) of expected information F given I_past."""
    F = np.asarray(F, float)
    I_past = np.asarray(I_past, float)
    if F.shape != I_past.shape or F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise TacestError(f"information matrices of different shapes {F.shape} and {I_past.shape}")
    if kind == "logdet":
        mu = np.linalg.eigvalsh(whitened(F, I_past))
        # F is positive semi-definite; rounding can leave tiny negative eigenvalues
        return float(np.sum(np.log1p(np.maximum(mu, 0.0))))
    if kind not in SCORES:
        raise TacestError(f"unknown score {kind!r}: use one of {', '.join(SCORES)}")
    C_past = np.linalg.inv(I_past)
    sig = np.sqrt(np.diag(C_past))
    Ip = I_past * np.outer(sig, sig)
    Fs = F * np.outer(sig, sig)
    post = 0.5 * (Ip + Fs + (Ip + Fs).T)
    if kind == "D":
        sign, logdet = np.linalg.slogdet(post)
        return float(logdet)
    if kind == "A":
        C_post = np.linalg.inv(post)
        return float(np.sum(1.0 - np.diag(C_post)))  # diag of the scaled C_past is 1
    lo_post = float(np.linalg.eigvalsh(post)[0])
    lo_past = float(np.linalg.eigvalsh(0.5 * (Ip + Ip.T))[0])
    return float(np.log(lo_post) - np.log(lo_past))
