"""How measurements inform the parameters and a reference state: four constructions on
one linearization, the same in 2-D and 3-D.

A :class:`Linearized` holds the whitened residuals r (R,) of a stretch of samples (a
predicted poke, or the recorded past) at a point, and their Jacobian split into the
*kept* columns a = (θ, s) — the parameters θ and a reference state s (the state where a
predicted poke starts, or where the past data end: "the current state") — and the
*nuisance* columns x (every other pose, velocity and contact impulse).  Its rows are
classed: *measured* rows (force, normal, contact flag, pose observation: what a sensor
reports) and *driving* rows (the physics of the violation-implicit loss: dynamics,
penetration, complementarity, dissipation, friction cone, kinematics: how the state
evolves).  The information about a, in the units of the kept columns:

``schur`` (the estimator's own, Laplace)
    F = J_aᵀJ_a − J_aᵀJ_x (J_xᵀJ_x + δI)⁻¹ J_xᵀJ_a over all rows: the states are
    marginalized jointly with every measurement (tacest.estimation.uncertainty).
``identity`` (the quasi-static identity-Jacobian approximation)
    the measured rows only, with every state moving rigidly with s and not with θ
    (∂x/∂s = S_id, ∂x/∂θ = 0): G = [J_θ, J_s + J_x S_id], F = GᵀG.
``diffsim`` (differentiating a simulation)
    ∂x/∂a is the response of the model's own simulation: the driving rows solved for the
    states, linearized (with the contact impulses held near their values by a weak prior,
    :attr:`Linearized.x_prior`): X = −(J_Dxᵀ J_Dx + P²)⁻¹ J_Dxᵀ J_Da, G = J_a + J_x X on the
    measured rows, F = GᵀG.
``marginal`` ("marginalize + sample")
    for each sample t, the score of its measurements m_t with the state x_t marginalized
    over the simulation's own spread, g_t = ∇_a log Σ_i p(m_t | x^i(a)), with x^i(a) =
    x̄ + X da + ε_i, ε_i drawn from the linearized transition N(0, (J_Dxᵀ J_Dx + P²)⁻¹)
    (antithetic pairs), and

        g_t = Σ_i softmax_i(log p(m_t | x^i)) · ∇_a log p(m_t | x^i)
            = −G_tᵀ Σ_i w_ti (r_t(x^i) − r_t(x̄) − n),

    the likelihood log p(m_t | x) = −½|r_t(x) − r_t(x̄) − n|² evaluated with the model's
    exact (nonlinear) residuals at the sampled states (:attr:`Linearized.residual_at`)
    and n the deviation of a data draw from the marginal (the residuals at one of the
    sampled states, in turn, plus whitened sensor noise: the state that made the data is
    among the weighted ones, as in the prior contrastive estimator of the information
    gain); F = Σ_t E_n[g_t g_tᵀ] (``draws`` data draws per sample, common random numbers).  Where the transition is tight the weights are
    uniform and g_t = G_tᵀ n: F is ``diffsim``'s, and on an object that does not move
    (∂x_t/∂s = I) ``identity``'s.  Where it is wide (a push of uncertain strength, a
    topple), m_t says less about a: for a linear model E_n[g gᵀ] = G_tᵀ(J_t Σ J_tᵀ + I)⁻¹G_t,
    the information of m_t with x_t integrated out (tests/test_sensitivity.py: within a
    few per cent).  Where the samples cannot resolve the posterior (a transition far
    wider than the sensor noise) the estimate lies between that and diffsim's: the
    posterior mean falls on the state that made the data.  Each sample is marginalized
    on its own (the other samples' measurements do not narrow its transition).  The weighted
    residual of a sample is never longer than its noise draw (exact for the linear
    model; longer ones are Monte Carlo error of degenerate weights, cut to that length:
    :func:`_clip_to_noise`).

The kept columns' units are the caller's (the dimension's information model converts to
physical units).  tests/test_sensitivity.py checks the limits above.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tacest.errors import TacestError
from tacest.estimation.uncertainty import RIDGE, schur_information

INFORMATION_METHODS = ("schur", "identity", "diffsim", "marginal")
#: state samples per marginalized sample (antithetic pairs: half as many independent
#: draws); 32 keeps the Monte Carlo error of a poke's logdet score to a few per cent on
#: tests/test_sensitivity.py's cases, far below the spread between candidate pokes
MARGINAL_SAMPLES = 32
#: measurement-noise draws per sample for E_n[g gᵀ]
MARGINAL_DRAWS = 8
#: the weak prior of the transition on contact impulses (diffsim, marginal): each
#: impulse variable is its value at the linearization point to within this fraction of
#: its size, and at least IMPULSE_FLOOR (in the model's impulse units, m0 g dt).  A push
#: whose strength the physics rows do not fix (the finger's impulse is free in them) then
#: moves the object as predicted, give or take half
IMPULSE_SPREAD = 0.5
IMPULSE_FLOOR = 0.05


@dataclass
class Linearized:
    """The linearized residuals of a stretch of samples (module docstring).

    Ja : (R, n_a) dense, kept columns θ (n_theta) then s (n_s); Jx : (R, n_x) sparse,
    nuisance columns; r : (R,) residuals at the point; measured, driving : (R,) bool row
    classes; sample : (R,) int, the sample each row belongs to; S_identity : (n_x, n_s)
    sparse, ∂x/∂s of the identity approximation (poses follow s, the rest 0);
    x_prior : (n_x,) square-root precision of the transition's weak prior on each
    nuisance variable (0: none); residual_at : callable(dx (n_x,)) -> (R,) the exact
    residuals at x̄ + dx, and (n_x, n) -> (R, n) column by column (None: the
    linearization, J_x dx, is used).
    """

    Ja: np.ndarray
    Jx: object
    r: np.ndarray
    measured: np.ndarray
    driving: np.ndarray
    sample: np.ndarray
    S_identity: object
    n_theta: int
    x_prior: np.ndarray = None
    residual_at: Optional[Callable] = None
    extra: dict = field(default_factory=dict)

    @property
    def n_a(self) -> int:
        return int(self.Ja.shape[1])

    @property
    def n_x(self) -> int:
        return int(self.Jx.shape[1])


def impulse_prior(values, spread: float = IMPULSE_SPREAD, floor: float = IMPULSE_FLOOR) -> np.ndarray:
    """(n,) square-root precisions 1 / max(spread·|value|, floor) of impulse variables."""
    return 1.0 / np.maximum(spread * np.abs(np.asarray(values, float)), floor)


def information(lin: Linearized, method: str = "schur", samples: int = MARGINAL_SAMPLES,
                draws: int = MARGINAL_DRAWS, seed: int = 0) -> np.ndarray:
    """(n_a, n_a) information about the kept columns by ``method`` (module docstring)."""
    if method == "schur":
        return schur_information(lin.Ja, lin.Jx)
    if method == "identity":
        G = identity_sensitivity(lin)
        return _sym(G.T @ G)
    if method == "diffsim":
        G, _ = simulated_sensitivity(lin)
        return _sym(G.T @ G)
    if method == "marginal":
        return marginal_information(lin, samples=samples, draws=draws, seed=seed)
    raise TacestError(f"unknown information method {method!r}: use {', '.join(INFORMATION_METHODS)}")


def _sym(A):
    A = np.asarray(A, float)
    return 0.5 * (A + A.T)


def identity_sensitivity(lin: Linearized) -> np.ndarray:
    """(R_m, n_a) G of the measured rows with ∂x/∂s = S_identity, ∂x/∂θ = 0."""
    m = np.asarray(lin.measured, bool)
    G = np.array(lin.Ja[m], float)
    Jm = sp.csr_matrix(lin.Jx)[np.nonzero(m)[0]]
    G[:, lin.n_theta:] += np.asarray((Jm @ sp.csc_matrix(lin.S_identity)).todense())
    return G


class _Transition:
    """The linearized transition of the driving rows: H = J_Dxᵀ J_Dx + P² (+ a ridge),
    factorized once, in coordinates whose columns have unit norm."""

    def __init__(self, lin: Linearized):
        d = np.asarray(lin.driving, bool)
        self.rows = np.nonzero(d)[0]
        JD = sp.csr_matrix(lin.Jx)[self.rows].tocsc()
        prior = np.zeros(lin.n_x) if lin.x_prior is None else np.asarray(lin.x_prior, float)
        norms = np.sqrt(np.asarray(JD.multiply(JD).sum(axis=0)).ravel() + prior ** 2)
        norms[norms == 0] = 1.0
        self.norms = norms
        self.JD = JD @ sp.diags(1.0 / norms)
        self.P = prior / norms
        H = (self.JD.T @ self.JD + sp.diags(self.P ** 2 + RIDGE)).tocsc()
        self.lu = spla.splu(H)
        self.JDa = np.asarray(lin.Ja[self.rows], float)

    def response(self) -> np.ndarray:
        """(n_x, n_a) ∂x/∂a: the driving rows' least-squares response to the kept columns."""
        Xs = -self.lu.solve(np.asarray(self.JD.T @ self.JDa))
        return Xs / self.norms[:, None]

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n_x, n) draws of N(0, H⁻¹) (physical nuisance units): ε = H⁻¹(J_Dᵀξ + Pζ),
        in antithetic pairs (ε, −ε)."""
        half = max(1, n // 2)
        xi = rng.standard_normal((self.JD.shape[0], half))
        zeta = rng.standard_normal((len(self.P), half))
        e = self.lu.solve(np.asarray(self.JD.T @ xi) + self.P[:, None] * zeta) / self.norms[:, None]
        return np.concatenate([e, -e], axis=1)


def simulated_sensitivity(lin: Linearized, transition: _Transition | None = None):
    """(G (R_m, n_a) of the measured rows with ∂x/∂a the simulation's response, the
    transition)."""
    tr = transition or _Transition(lin)
    X = tr.response()
    m = np.asarray(lin.measured, bool)
    Jm = sp.csr_matrix(lin.Jx)[np.nonzero(m)[0]]
    G = np.asarray(lin.Ja[m], float) + np.asarray(Jm @ X)
    return G, tr


def marginal_information(lin: Linearized, samples: int = MARGINAL_SAMPLES, draws: int = MARGINAL_DRAWS,
                         seed: int = 0) -> np.ndarray:
    """F of the ``marginal`` construction (module docstring)."""
    G, tr = simulated_sensitivity(lin)
    m_rows = np.nonzero(np.asarray(lin.measured, bool))[0]
    if len(m_rows) == 0:
        return np.zeros((lin.n_a, lin.n_a))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 28]))

    def deviations(eps):
        """(R_m, n) change of the measured rows at the states x̄ + eps (n_x, n)."""
        if lin.residual_at is None:
            d = np.asarray(sp.csr_matrix(lin.Jx)[m_rows] @ eps)
        else:
            r0 = np.asarray(lin.r, float)[m_rows]
            d = np.asarray(lin.residual_at(eps), float)[m_rows] - r0[:, None]
        return np.where(np.isfinite(d), d, 0.0)

    dR = deviations(tr.sample(int(samples), rng))  # (R_m, N): the state samples x^i
    # data drawn from the marginal: the state of one of the samples (in turn), then
    # whitened sensor noise, so that E_n[g gᵀ] is the information of m_t with x_t
    # integrated out.  The state that made the data is among the weighted samples (as in
    # the prior contrastive estimator of the information gain, Foster et al. 2020): where
    # the weights degenerate (a transition much wider than the sensor noise), the
    # posterior mean falls on it and g_t tends to diffsim's G_tᵀn instead of growing with
    # the spread of the samples
    K = int(draws)
    n = dR[:, np.arange(K) % dR.shape[1]] + rng.standard_normal((len(m_rows), K))
    samp = np.asarray(lin.sample)[m_rows]
    groups, t_of_row = np.unique(samp, return_inverse=True)
    A = sp.csr_matrix((np.ones(len(m_rows)), (t_of_row, np.arange(len(m_rows)))), shape=(len(groups), len(m_rows)))
    E = (dR[:, :, None] - n[:, None, :]) ** 2  # (R_m, N, K)
    logw = -0.5 * np.asarray(A @ E.reshape(len(m_rows), -1)).reshape(len(groups), dR.shape[1], int(draws))
    logw -= logw.max(axis=1, keepdims=True)
    w = np.exp(logw)
    w /= w.sum(axis=1, keepdims=True)  # (n_t, N, K): softmax over the state samples
    resid = np.einsum("rik,rik->rk", w[t_of_row], dR[:, :, None] - n[:, None, :])  # (R_m, K)
    resid = _clip_to_noise(resid, n, A)
    # g_tk = -Σ_{rows r of t} G_r resid_rk; F = Σ_t mean_k g_tk g_tkᵀ
    contrib = G[:, None, :] * resid[:, :, None]  # (R_m, K, n_a)
    g = np.asarray(A @ contrib.reshape(len(m_rows), -1)).reshape(len(groups), int(draws), lin.n_a)
    F = np.einsum("tki,tkj->ij", g, g) / int(draws)
    return _sym(F)


def _clip_to_noise(resid: np.ndarray, n: np.ndarray, A) -> np.ndarray:
    """(R_m, K) the weighted residuals e_tk = Σ_i w_ti (r_t(x^i) − r_t(x̄)) − n_tk, each
    sample's vector shortened to at most the length of its noise draw |n_tk|.

    For a linear model the exact posterior mean gives e = −(C_t + I)⁻¹ n with C_t ≽ 0 the
    state's spread seen in the measurement, so |e| <= |n| always: marginalizing the state
    never adds information about a sample beyond what its noise allows.  Longer vectors
    come from Monte Carlo error when the weights degenerate (a transition much wider than
    the measurement noise leaves every state sample far from the data) and would inflate
    F by the spread of the samples instead of shrinking it; they are cut to |n|.
    A : (n_t, R_m) 0/1 map of rows to their sample."""
    e2 = np.asarray(A @ resid ** 2)  # (n_t, K) squared lengths per sample and draw
    n2 = np.asarray(A @ n ** 2)
    scale = np.sqrt(np.minimum(1.0, n2 / np.maximum(e2, 1e-300)))
    return resid * np.asarray(A.T @ scale)
