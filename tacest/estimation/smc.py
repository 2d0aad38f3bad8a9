"""What the 2-D and 3-D sequential Monte Carlo starts share (tacest.estimation.smc2d,
tacest.estimation.smc3d): the hypotheses' parameters (box extents, mass, frictions)
with their weights, systematic resampling and parameter jitter; the tactile likelihood
of a touching or non-touching fingertip; which fingertips are near.  The motion of the
hypotheses (their poses and velocities) and the contact geometry are each dimension's.
"""

from __future__ import annotations

import numpy as np

from tacest.io.run import Run

#: resample when the effective sample size falls below this fraction of the particles
ESS_FRACTION = 0.5
#: m, sigma of the fingertip's gap to the surface in the sampler's likelihood: looser
#: than the NLP's contact sigma (0.5 mm), for the forward model's penalty contacts sink
#: a fingertip ~1 mm into a hypothesis that pushes it
SIGMA_GAP = 2e-3
#: rad, sigma of the contact normal in the sampler's likelihood (looser than the NLP's
#: 0.05: a hypothesis a few degrees off in the middle of a topple is still the right one)
SIGMA_NORMAL = 0.15
#: jitter of a resampled hypothesis: log-extents, log-mass, frictions, position (m),
#: angle (rad), velocity (m/s, rad/s)
JITTER = {"log_extent": 0.01, "log_mass": 0.03, "friction": 0.02, "position": 3e-4, "angle": 5e-3,
          "velocity": 5e-3, "omega": 0.05}
#: range of the starting extents, as factors of the length scale L (log-uniform), and of
#: the frictions
EXTENT_RANGE = (0.4, 2.5)
FRICTION_RANGE = (0.1, 1.0)
#: m/s, rad/s: speed below which a hypothesis counts as at rest (samples with every
#: hypothesis at rest and no fingertip near are skipped)
REST_SPEED = 1e-4
REST_OMEGA = 1e-3


class ParticleParameters:
    """N hypotheses' parameters: box extents (N, D) m, mass (N,) kg, mu_g, mu_f (N,);
    their log weights and accumulated log likelihoods (N,).

    Half the extents are log-uniform over EXTENT_RANGE · L, half around ``extents0``
    (D,) m (where the touches already tell the extents, there); the mass is m0 times a
    log-normal draw where forces are measured, else m0 (not identifiable)."""

    def __init__(self, n, rng, L, m0, has_force, extents0):
        self.rng = rng
        D = len(extents0)
        lo, hi = np.log(EXTENT_RANGE[0] * L), np.log(EXTENT_RANGE[1] * L)
        k = n // 2
        self.extents = np.exp(np.concatenate([rng.uniform(lo, hi, size=(n - k, D)),
                                              np.log(extents0)[None] + rng.normal(0, 0.25, size=(k, D))]))
        self.extents = np.clip(self.extents, EXTENT_RANGE[0] * L, EXTENT_RANGE[1] * L)
        self.mass = m0 * (np.exp(rng.normal(0.0, 0.7, size=n)) if has_force else np.ones(n))
        self.mu_g = rng.uniform(*FRICTION_RANGE, size=n)
        self.mu_f = rng.uniform(*FRICTION_RANGE, size=n)
        self.has_force = has_force
        self.log_w = np.zeros(n)
        self.log_lik = np.zeros(n)

    @property
    def n(self):
        return len(self.mass)

    def take(self, idx):
        """A copy holding only the hypotheses idx."""
        out = type(self).__new__(type(self))
        out.__dict__.update({k: (v[idx] if isinstance(v, np.ndarray) and v.shape[:1] == (self.n,) else v)
                             for k, v in self.__dict__.items()})
        return out

    def resample_parameters(self) -> np.ndarray:
        """Systematic resampling of the parameters, then their jitter (JITTER); the
        weights reset.  Returns the (N,) indices the caller reorders its states with."""
        w = np.exp(self.log_w - self.log_w.max())
        w /= w.sum()
        u = (self.rng.random() + np.arange(self.n)) / self.n
        idx = np.minimum(np.searchsorted(np.cumsum(w), u), self.n - 1)
        j, n, rng = JITTER, self.n, self.rng
        self.extents = self.extents[idx] * np.exp(rng.normal(0, j["log_extent"], size=(n, self.extents.shape[1])))
        if self.has_force:
            self.mass = self.mass[idx] * np.exp(rng.normal(0, j["log_mass"], size=n))
        else:
            self.mass = self.mass[idx]
        self.mu_g = np.clip(self.mu_g[idx] + rng.normal(0, j["friction"], size=n), 0.02, 2.0)
        self.mu_f = np.clip(self.mu_f[idx] + rng.normal(0, j["friction"], size=n), 0.02, 2.0)
        self.log_lik = self.log_lik[idx]
        self.log_w = np.zeros(n)
        return idx

    def ess(self):
        w = np.exp(self.log_w - self.log_w.max())
        w /= w.sum()
        return 1.0 / float(np.sum(w * w))


def subtract_touch_terms(ll, touching: bool, gap, normal__world, measured_normal, settings) -> None:
    """Subtract from ll (N,) the negative log likelihood of one fingertip's contact flag
    and normal: touching, its gap (N,) m to each hypothesis' surface (sigma_gap) and the
    surface normal (N, D) against the measured one (sigma_normal, where measured); not
    touching, only a gap below zero (the fingertip inside the hypothesis)."""
    if touching:
        ll -= 0.5 * (gap / settings.sigma_gap) ** 2
        if np.all(np.isfinite(measured_normal)):
            ll -= 0.5 * np.sum((normal__world - measured_normal) ** 2, axis=1) / settings.sigma_normal ** 2
    else:
        ll -= 0.5 * (np.minimum(gap, 0.0) / settings.sigma_gap) ** 2


def fingers_near(run: Run, t: int, position, reach: float) -> list:
    """Fingers whose centre at sample t-1 or t is within ``reach`` m of any hypothesis'
    centre ``position`` (N, D) m (a finger whose position is missing is not near)."""
    out = []
    for f in range(run.n_fingers):
        c = run.finger_position[[max(t - 1, 0), t], f]
        if not np.all(np.isfinite(c)):
            continue
        if np.min(np.linalg.norm(position[None] - c[:, None], axis=-1)) <= reach:
            out.append(f)
    return out


#: two sampler runs whose best boxes agree within this fraction in every extent give
#: one start, not two
SAME_BOX = 0.02


def best_lineages(results: list, n: int) -> list:
    """The ``n`` sampler results (smc2d.SMCResult or smc3d.SMC3DResult, one per seeded
    run) of highest log likelihood, a result whose box is within SAME_BOX of a better
    one's left out; returned in the runs' order (their seeds'), so that where every run
    is kept the starts are the runs in turn."""
    kept = []
    for i in sorted(range(len(results)), key=lambda i: -results[i].log_likelihood):  # stable: equals by seed
        r = results[i]
        if len(kept) < n and all(np.max(np.abs(r.extents / results[j].extents - 1.0)) > SAME_BOX for j in kept):
            kept.append(i)
    return [results[i] for i in sorted(kept)]
