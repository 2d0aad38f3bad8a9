"""Where the model and the data disagree: fitted residuals against the noise floor.

Every loss term of the estimator is a whitened residual r (divided by its noise
level), stored per sample as 0.5·‖r‖² (``RunEstimate.residuals``).  If the model and
the noise levels were right, ‖r‖² summed over a set of samples would be a chi-square
variable with as many degrees of freedom as it has components: its *noise floor*.

Degrees of freedom (:func:`residual_dof`), per sample and term (2-D; in 3-D the stage
terms start a sample later, see the function):

=================  ==========================================================
force              D per finger with a force reading (D = 2 or 3 components)
normal             D-1 per finger in contact (a unit vector: its angles)
contact            1 per finger (gap where the flag is 1, overlap where 0)
pose               3 (2-D) or 6 (3-D) where a pose was observed
dynamics           3 (2-D) or 6 (3-D) (the first: the rest residual, 0 for a run that
                   starts free, pose-observed: estimation.data.starts_at_rest)
penetration        1 per shape vertex (one-sided penalty)
complementarity    1 per shape vertex (sample 0: none)
dissipation        1 per finger (sample 0: none)
cone               2 per finger in 2-D (both edges), 1 in 3-D (sample 0: none)
=================  ==========================================================

Windows.  Each run is cut into windows of one contact state (some finger touching, or
none) of at most ``window`` samples (:func:`contact_windows`).  With ‖r‖² sum S over n
degrees of freedom in a window, the floor says S ~ mu·χ²(n).

Two floors (``mode``):

``nominal``
    mu = 1: the configured noise levels exactly (``tacest/configs/estimate.toml`` [noise]).
    The test is exact for whitened noise at those levels; it flags only what exceeds
    them.  A fit absorbs part of the noise and the configured levels are generous, so
    on real fits this floor is far above most residuals.
``calibrated`` (default)
    mu per term and contact state from the data: the median over windows of
    S / median(χ²(n)) (pure whitened noise gives 1), capped at 1 (the configured level:
    an excess spread everywhere is still measured against it) and floored at MU_MIN.
    Windows that scatter more than a chi-square allows (a fit's residuals are
    correlated in time) widen the test: with the robust spread phi of
    (S/mu − n) / sqrt(2n) over the windows (phi >= 1), S / (mu·phi²) ~ χ²(n / phi²)
    (a scaled chi-square with the same mean and phi² times the variance).

Test.  p = P(χ²(n/phi²) >= S / (mu·phi²)); windows are flagged with Bonferroni's
correction over all (window, term) tests: with residuals that follow the floor, the
chance that anything at all is flagged is at most ``alpha`` (the stated false-alarm
rate; with the calibrated floor, up to the error of its estimated mu and phi).

Share.  Excess in objective units (weight × 0.5·(S − mu·n)); the share of a flagged
window is its excess divided by the summed excess of all flagged windows (what stands
out, located); :func:`excess_summary` says how much of the net excess of all windows
the flagged ones hold (the rest is spread thinly, below the tests' reach).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from tacest.estimation.data import starts_at_rest

#: default family-wise false-alarm rate of the window tests (probability that a
#: diagnosis of pure noise flags anything)
ALPHA = 0.01
#: default longest window, samples (0.2 s at 100 Hz: a poke's contact phase is 0.3-1 s,
#: an impact or a sensor delay a few samples)
WINDOW = 20

#: smallest calibrated floor level per degree of freedom: 1 % of the configured noise
#: variance (a tenth of its sigma).  Below it a fitted residual is at the solver's
#: tolerance, and a floor of ~0 would make any rounding look significant.
MU_MIN = 1e-2
#: floor modes (see module doc)
MODES = ("calibrated", "nominal")

#: the loss terms in the estimator's order (tacest.estimation.problem.SQUARED_TERMS)
TERMS = ("force", "normal", "contact", "pose", "dynamics", "penetration", "complementarity", "dissipation", "cone")


def residual_dof(run, n_vertices: int) -> dict:
    """{term: (T,) float} degrees of freedom per sample (see the module table).

    run : tacest.io.run.Run (2-D or 3-D); n_vertices : K of the fitted shape.  The
    stage terms start at the first dynamic interval: sample 1 in 2-D (one interval per
    sample pair), sample 2 in 3-D (velocities from two intervals; its rest term sits at
    sample 1).
    """
    T, F = run.n_samples, run.n_fingers
    D = run.dim
    first = 1 if D == 2 else 2  # first sample with stage (interval) terms
    n_pose = 3 if D == 2 else 6  # pose residual and body velocity components
    dof = {t: np.zeros(T) for t in TERMS}
    if F:
        valid = ~run.finger_missing_mask  # (T, F)
        on = run.contact.astype(bool) & valid
        if run.force is not None:
            dof["force"][first:] = D * valid[first:].sum(axis=1)
        dof["normal"][first:] = (D - 1) * on[first:].sum(axis=1)  # a unit vector's angles
        dof["contact"][:] = valid.sum(axis=1)
        dof["dissipation"][first:] = F
        dof["cone"][first:] = (2 if D == 2 else 1) * F  # 2-D: both edges of the cone
    if run.pose_obs is not None:
        dof["pose"][:] = n_pose * np.all(np.isfinite(run.pose_obs), axis=1)
    dof["dynamics"][first:] = n_pose
    dof["dynamics"][first - 1] = n_pose if starts_at_rest(run) else 0  # the rest prior
    if D == 3:
        dof["dynamics"][0] = 0
    dof["penetration"][:] = n_vertices
    dof["complementarity"][first:] = n_vertices
    return dof


def contact_state(run) -> np.ndarray:
    """(T,) bool: some finger touched (flag 1 and the reading arrived)."""
    if run.contact is None:
        return np.zeros(run.n_samples, bool)
    return np.any(run.contact.astype(bool) & ~run.finger_missing_mask, axis=1)


def contact_windows(state: np.ndarray, window: int = WINDOW) -> list:
    """[(start, stop, state), ...] tiling range(T): runs of equal contact state, each cut
    into pieces of at most ``window`` samples (as equal as possible)."""
    state = np.asarray(state, bool)
    T = len(state)
    out = []
    a = 0
    while a < T:
        b = a + 1
        while b < T and state[b] == state[a]:
            b += 1
        n_pieces = int(np.ceil((b - a) / window))
        edges = np.linspace(a, b, n_pieces + 1).round().astype(int)
        out += [(int(s), int(e), bool(state[a])) for s, e in zip(edges[:-1], edges[1:]) if e > s]
        a = b
    return out


@dataclass
class WindowStat:
    """One (run, window, term) test.  S, n, expected in ‖r‖² units; excess in objective
    units (weight × 0.5 × (S − expected)); p: its p-value; share: of the flagged excess."""

    run: int
    start: int
    stop: int
    term: str
    contact: bool
    S: float
    n: float
    expected: float
    excess: float
    p: float
    flagged: bool = False
    share: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


def chi2_median(n):
    """Median of a chi-square variable with n (> 0) degrees of freedom.  (scipy.special's
    chi-square functions: the same numbers as scipy.stats.chi2, whose import costs every
    estimate 0.4-0.8 s.)"""
    from scipy.special import chdtri

    return chdtri(np.asarray(n, float), 0.5)


def chi2_pvalue(S, n, mu=1.0, phi=1.0):
    """P(χ²(n/phi²) >= S/(mu·phi²)), elementwise; for n = 0: 1 if S is 0, else 0 (a
    residual that has no degrees of freedom should be exactly zero)."""
    from scipy.special import chdtrc

    S, n, mu, phi = np.broadcast_arrays(*(np.asarray(x, float) for x in (S, n, mu, phi)))
    out = np.ones(S.shape)
    pos = n > 0
    f2 = phi[pos] ** 2
    out[pos] = chdtrc(n[pos] / f2, S[pos] / (mu[pos] * f2))
    out[~pos & (S > 1e-12)] = 0.0
    return out


def _key(term, state):
    return f"{term}|{'contact' if state else 'free'}"


@dataclass
class FloorModel:
    """Noise floor: level per degree of freedom ``mu`` and dispersion ``phi`` (>= 1) per
    term and contact state (keys ``term|contact`` and ``term|free``), ``mode``, the
    robust levels before capping (``robust``), loss weights, window length."""

    mu: dict
    phi: dict
    robust: dict
    weights: dict
    windows: int = WINDOW
    mode: str = "calibrated"

    def level(self, term: str, state: bool) -> float:
        return float(self.mu.get(_key(term, state), 1.0))

    def dispersion(self, term: str, state: bool) -> float:
        return float(self.phi.get(_key(term, state), 1.0))

    def expected_series(self, term: str, dof, state) -> np.ndarray:
        """(T,) expected ‖r‖² per sample of degrees of freedom ``dof`` (T,) in contact
        states ``state`` (T,) bool."""
        state = np.asarray(state, bool)
        mu = np.where(state, self.level(term, True), self.level(term, False))
        return mu * np.asarray(dof, float)

    def bulk_level(self, term: str, state: bool) -> float:
        """The level most windows sit at, min(1, robust level), without the test's lower
        limit MU_MIN (0 where no window had degrees of freedom)."""
        r = self.robust.get(_key(term, state), float("nan"))
        return float(min(1.0, r)) if np.isfinite(r) else 0.0

    def objective_floor(self, dof: dict, state) -> float:
        """Expected objective (Σ weight × 0.5 ‖r‖²) of samples with dof {term: (T,)} and
        contact states (T,) at the bulk levels (:meth:`bulk_level`): the floor of the
        held-out gap, the same in both modes."""
        state = np.asarray(state, bool)
        total = 0.0
        for t, d in dof.items():
            lev = np.where(state, self.bulk_level(t, True), self.bulk_level(t, False))
            total += self.weights.get(t, 1.0) * 0.5 * float(np.sum(lev * np.asarray(d, float)))
        return float(total)

    def term_level(self, term: str) -> str:
        """Short text of a term's levels (contact / free; "–" where no window had
        degrees of freedom)."""
        def one(state):
            r = self.robust.get(_key(term, state), float("nan"))
            return f"{self.level(term, state):.3g}" if np.isfinite(r) else "–"

        return f"{one(True)}/{one(False)}"

    def to_dict(self) -> dict:
        return {"mode": self.mode, "mu": dict(self.mu), "phi": dict(self.phi), "robust_level": dict(self.robust),
                "window": self.windows}


def _windows_of(residuals, dofs, states, window, term):
    """(S (N,), n (N,), state (N,)) of every window of one term over all runs."""
    S, n, st = [], [], []
    for res, dof, state in zip(residuals, dofs, states):
        if term not in res or term not in dof:
            continue
        S_all = 2.0 * np.asarray(res[term], float)
        d_all = np.asarray(dof[term], float)
        for a, b, c in contact_windows(state, window):
            S.append(float(S_all[a:b].sum()))
            n.append(float(d_all[a:b].sum()))
            st.append(bool(c))
    return np.array(S), np.array(n), np.array(st, bool)


def fit_floor(residuals: list, dofs: list, states: list, weights: dict = None, window: int = WINDOW,
              mode: str = "calibrated") -> FloorModel:
    """The noise floor of fitted residuals (see module doc).

    residuals : per run {term: (T,) 0.5·‖r‖² per sample}; dofs : per run {term: (T,)};
    states : per run (T,) bool contact state; mode : ``calibrated`` or ``nominal``.
    """
    from tacest.errors import TacestError

    if mode not in MODES:
        raise TacestError(f"floor mode must be one of {', '.join(MODES)}, got {mode!r}")
    weights = dict(weights or {})
    mu, phi, robust = {}, {}, {}
    for term in TERMS:
        S, n, st = _windows_of(residuals, dofs, states, window, term)
        for state in (True, False):
            k = _key(term, state)
            sel = (st == state) & (n > 0)
            if not np.any(sel):
                mu[k], phi[k], robust[k] = 1.0, 1.0, float("nan")
                continue
            level = float(np.median(S[sel] / chi2_median(n[sel])))
            robust[k] = level
            if mode == "nominal":
                mu[k], phi[k] = 1.0, 1.0
                continue
            m = float(np.clip(level, MU_MIN, 1.0))
            z = (S[sel] / m - n[sel]) / np.sqrt(2.0 * n[sel])
            spread = 1.4826 * float(np.median(np.abs(z - np.median(z)))) if z.size >= 3 else 1.0
            mu[k], phi[k] = m, max(1.0, spread)
    return FloorModel(mu=mu, phi=phi, robust=robust, weights=weights, windows=window, mode=mode)


def window_tests(residuals: list, dofs: list, states: list, floor: FloorModel, alpha: float = ALPHA,
                 run_ids: list = None) -> list:
    """Every (run, window, term) test, flagged with Bonferroni's correction at ``alpha``,
    with shares of the positive excess.  Returns a list of :class:`WindowStat`."""
    stats = []
    mus, phis = [], []
    run_ids = list(range(len(residuals))) if run_ids is None else list(run_ids)
    for rid, res, dof, st in zip(run_ids, residuals, dofs, states):
        wins = contact_windows(st, floor.windows)
        for term in TERMS:
            if term not in res or term not in dof:
                continue
            S_all = 2.0 * np.asarray(res[term], float)
            d_all = np.asarray(dof[term], float)
            w = floor.weights.get(term, 1.0)
            for a, b, c in wins:
                S = float(S_all[a:b].sum())
                n = float(d_all[a:b].sum())
                if n == 0 and S <= 1e-12:
                    continue
                m = floor.level(term, c)
                E = m * n
                stats.append(WindowStat(run=rid, start=a, stop=b, term=term, contact=c, S=S, n=n, expected=E,
                                        excess=w * 0.5 * (S - E), p=1.0))
                mus.append(m)
                phis.append(floor.dispersion(term, c))
    if not stats:
        return stats
    p = chi2_pvalue([s.S for s in stats], [s.n for s in stats], mus, phis)
    threshold = alpha / len(stats)
    for s, pv in zip(stats, p):
        s.p = float(pv)
        s.flagged = bool(pv < threshold and s.excess > 0)
    total = sum(s.excess for s in stats if s.flagged)
    for s in stats:
        s.share = float(s.excess / total) if s.flagged and total > 0 else 0.0
    return stats


def excess_summary(stats: list) -> dict:
    """Net excess over the floor of all windows (objective units), of the flagged ones,
    and the fraction of the net excess the flagged windows hold (None when the net
    excess is not positive)."""
    net = float(sum(s.excess for s in stats))
    flagged = float(sum(s.excess for s in stats if s.flagged))
    return {"net_excess": net, "flagged_excess": flagged, "flagged_fraction": flagged / net if net > 0 else None}


def flagged_windows(stats: list, merge: bool = True) -> list:
    """The flagged tests, largest share first; with ``merge``, adjacent flagged windows
    of the same run and term are joined (shares and excesses add, p is the smallest)."""
    flagged = sorted((s for s in stats if s.flagged), key=lambda s: (s.run, s.term, s.start))
    if merge:
        merged = []
        for s in flagged:
            last = merged[-1] if merged else None
            if last is not None and last.run == s.run and last.term == s.term and last.stop == s.start:
                merged[-1] = WindowStat(run=s.run, start=last.start, stop=s.stop, term=s.term,
                                        contact=last.contact or s.contact, S=last.S + s.S, n=last.n + s.n,
                                        expected=last.expected + s.expected, excess=last.excess + s.excess,
                                        p=min(last.p, s.p), flagged=True, share=last.share + s.share)
            else:
                merged.append(WindowStat(**asdict(s)))
        flagged = merged
    return sorted(flagged, key=lambda s: -s.share)


def breakdown(stats: list, floor: FloorModel) -> list:
    """Totals per (run, term, contact state): S, n, expected, excess and the p-value of
    the total under the floor.  A list of dicts, largest excess first."""
    groups = {}
    for s in stats:
        key = (s.run, s.term, s.contact)
        g = groups.setdefault(key, {"run": s.run, "term": s.term, "contact": s.contact, "S": 0.0, "n": 0.0,
                                    "expected": 0.0, "excess": 0.0, "windows": 0, "flagged": 0})
        g["S"] += s.S
        g["n"] += s.n
        g["expected"] += s.expected
        g["excess"] += s.excess
        g["windows"] += 1
        g["flagged"] += int(s.flagged)
    rows = list(groups.values())
    if rows:
        p = chi2_pvalue([r["S"] for r in rows], [r["n"] for r in rows],
                        [floor.level(r["term"], r["contact"]) for r in rows],
                        [floor.dispersion(r["term"], r["contact"]) for r in rows])
        for r, pv in zip(rows, p):
            r["p"] = float(pv)
    return sorted(rows, key=lambda r: -r["excess"])
