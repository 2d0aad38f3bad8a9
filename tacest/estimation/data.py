"""Turn run files into the NLP's parameter vector (data are parameters, never variables)."""

from __future__ import annotations



import numpy as np

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.io.run import Run
from tacest.model.effect import Scales
from tacest.model.priors import prior_head
from tacest.model.stage2d import G, G_NAMES, TERMS


def gravity_of(run: Run) -> float:
    """m/s², the magnitude of the run's gravity (SPEC attr ``gravity``)."""
    return float(np.linalg.norm(np.asarray(run.gravity, float)))


def choose_scales(runs: list[Run], config: EstimatorConfig) -> Scales:
    """Length scale from the prior size hint (or the config default); mass from the
    prior; gravity the runs' (their median magnitude)."""
    sizes = [float(r.prior["size"]) for r in runs if "size" in r.prior]
    L = float(np.median(sizes)) if sizes else config.prior.size
    masses = [float(r.prior["mass"]) for r in runs if "mass" in r.prior]
    m0 = float(np.median(masses)) if masses else config.prior.mass
    return Scales(L=L, m0=m0, g=float(np.median([gravity_of(r) for r in runs])))


#: half-width (samples) of the fingertip velocity filter: a least-squares line over
#: 2·h+1 samples; at 100 Hz and 0.1 mm position noise, h = 3 gives ~2 mm/s velocity
#: noise (vs ~14 mm/s for a plain difference), far below poke speeds of cm/s
FINGER_VELOCITY_HALF_WIDTH = 3


def force_in_contact(runs: list[Run]) -> bool:
    """Whether some run measured a fingertip's force while it touched the object: the one
    measurement that tells the mass.  Every other impulse scales with the mass, and so
    does every physics residual in units of the reference weight: without such a force a
    free mass only shrinks the physics' misfit (a pose-observed toss with a force stream
    the finger never used ended at 0.004 kg for 0.48, still creeping after 3000 IPOPT
    iterations).  A force stream without a touch tells nothing of the mass."""
    return any(r.force is not None and r.contact is not None and bool(np.any(r.contact)) for r in runs)


def finger_velocity(run: Run) -> np.ndarray:
    """(T, F, D) fingertip velocity, m/s: slope of a least-squares line through the
    samples within ±FINGER_VELOCITY_HALF_WIDTH (shorter windows at the ends)."""
    fp = run.finger_position
    T = fp.shape[0]
    h = FINGER_VELOCITY_HALF_WIDTH
    v = np.zeros_like(fp)
    k = np.arange(-h, h + 1, dtype=float)
    if T > 2 * h:  # the full windows at once: the slope sum_k k x[t+k] / (dt sum_k k^2)
        v[h: T - h] = sum(kk * fp[j: T - 2 * h + j] for j, kk in enumerate(k)) / (run.dt * np.sum(k * k))
    for t in (*range(min(h, T)), *range(max(h, T - h), T)):  # the shorter windows at the ends
        a, b = max(0, t - h), min(T, t + h + 1)
        if b - a < 2:
            continue
        tt = np.arange(a, b) * run.dt
        tt = tt - tt.mean()
        v[t] = np.tensordot(tt, fp[a:b] - fp[a:b].mean(0), axes=(0, 0)) / np.sum(tt * tt)
    return v


def touching(run: Run) -> np.ndarray:
    """(T, F) bool: the tactile flag is 1 and that finger's data of the sample arrived
    (not in /quality/missing_finger, or /quality/missing for a run without it)."""
    return run.contact.astype(bool) & ~run.finger_missing_mask


def touch_inconsistency(run: Run, gaps: np.ndarray) -> np.ndarray:
    """(N,) m²: how badly N candidate fingertip gaps (N, T, F) m disagree with the
    contact flags: the sum over samples of max(gap, 0)² where a fingertip touched and
    min(gap, 0)² where it did not (and its data arrived: placeholders of a missing
    finger, /quality/missing_finger or /quality/missing, count neither way)."""
    on = touching(run)
    off = ~run.contact.astype(bool) & ~run.finger_missing_mask
    return np.sum(np.where(on[None], np.maximum(gaps, 0), 0) ** 2, axis=(1, 2)) \
        + np.sum(np.where(off[None], np.minimum(gaps, 0), 0) ** 2, axis=(1, 2))


def touch_ends(run: Run) -> np.ndarray:
    """(T, F) bool: the last sample of each touch: the flag is 1 there (and the finger's
    data arrived, :func:`touching`) and not at the next sample (0, missing, or the run's
    end).  Its interval is the one in which the fingertip let go (or struck and bounced,
    for a touch of one sample): the model checks the flag there by the smaller of the
    gaps at the interval's two ends (tacest.dynamics.laws.contact_residual)."""
    on = touching(run)
    ends = on.copy()
    ends[:-1] &= ~on[1:]
    return ends


def finger_start_positions(run: Run) -> np.ndarray:
    """(T, F, D) m: each fingertip's position at the start of the sample's interval, the
    previous sample's (the first sample's own)."""
    fp = run.finger_position
    start = fp.copy()
    start[1:] = fp[:-1]
    return start


def starts_at_rest(run: Run) -> bool:
    """Whether the estimator holds the run's sample 0 at rest (the rest prior, noise
    ``rest``): only where nothing measures it.  A run whose first sample's pose is
    observed (e.g. an object tossed and seen by motion capture) starts free: the
    observations give its velocity (the 3-D estimator's rule too)."""
    if run.pose_obs is None:
        return True
    return not bool(np.all(np.isfinite(run.pose_obs[0])))


def pose_observation_columns(run: Run):
    """(obs (T, 3), weight (T, 1)): 2-D pose observations with the angle unwrapped and
    missing rows zeroed, and 1 where a row was observed (zeros without observations)."""
    T = run.n_samples
    if run.pose_obs is None:
        return np.zeros((T, 3)), np.zeros((T, 1))
    obs = run.pose_obs.copy()
    ok = np.all(np.isfinite(obs), axis=1)
    if ok.any():
        obs[ok, 2] = np.unwrap(obs[ok, 2])
    obs[~ok] = 0.0
    return obs, ok.astype(float)[:, None]


def data_matrix(run: Run, F: int) -> np.ndarray:
    """(T, n_data) per-sample data in the layout of :meth:`Problem2D.n_data`."""
    T = run.n_samples
    cols = []
    if F:
        fp = run.finger_position
        contact = run.contact.astype(float)
        valid = 1.0 - run.finger_missing_mask.astype(float)  # (T, F): 0 where that finger's data are unknown
        n_meas = np.where(np.isfinite(run.normal), run.normal, 0.0)
        force = run.force if run.force is not None else np.zeros_like(fp)
        w_force = np.zeros((T, F)) if run.force is None else valid.copy()
        w_tact = valid.copy()
        contact = contact * w_tact
        cols += [fp.reshape(T, -1), finger_velocity(run).reshape(T, -1), contact, n_meas.reshape(T, -1),
                 force.reshape(T, -1), w_force, w_tact, np.repeat(run.finger_radius[None, :], T, 0),
                 finger_start_positions(run).reshape(T, -1), touch_ends(run).astype(float)]
    cols += list(pose_observation_columns(run))
    D = np.concatenate(cols, axis=1)
    return D


def global_vector(run: Run, scales: Scales, config: EstimatorConfig, eps: float, comp_mult: float,
                  dyn_mult: float = 1.0) -> np.ndarray:
    nz = config.noise
    g = np.zeros(len(G_NAMES))
    up = run.up
    grav = gravity_of(run)
    vals = dict(dt=run.dt, L=scales.L, Lam=scales.m0 * grav * run.dt, m0=scales.m0, nx=up[0], ny=up[1],
                h=run.ground_height, sig_force=nz.force, sig_normal=nz.normal, sig_gap=nz.contact_gap,
                sig_proc=nz.process, sig_pen=nz.penetration, sig_rest=nz.rest,
                w_rest=1.0 if starts_at_rest(run) else 0.0,
                sig_pos=run.sigma_position, sig_ang=run.sigma_angle, eps=eps, comp_mult=comp_mult,
                dyn_mult=dyn_mult, sig_comp=nz.complementarity, sig_diss=nz.dissipation,
                m_ref=scales.m0, I_ref=scales.m0 * scales.L ** 2 / 6, sig_diss_g=nz.dissipation_ground,
                reach=nz.complementarity_reach, grav=grav,
                gx=float(run.gravity[0]), gy=float(run.gravity[1]))
    for k, v in vals.items():
        g[G[k]] = v
    return g


def parameter_vector(problem, runs: list[Run], scales: Scales, config: EstimatorConfig,
                     eps: float, comp_mult: float, s_ref: np.ndarray, weights_override: dict | None = None,
                     dyn_mult: float = 1.0, ridge: float | None = None):
    """The full parameter vector p of a tacest.estimation.problem2d.Problem2D's NLP."""
    if len(runs) != len(problem.structures):
        raise TacestError("internal: runs do not match the problem structure")
    parts = [np.array([scales.L, scales.m0])]
    for run, st in zip(runs, problem.structures):
        if run.n_samples != st.T:
            raise TacestError("internal: run length does not match the problem structure")
        parts.append(global_vector(run, scales, config, eps, comp_mult, dyn_mult))
        parts.append(data_matrix(run, st.F).reshape(-1))
    w = config.weights
    wd = {t: getattr(w, t) for t in TERMS}
    wd.update(weights_override or {})
    # (a problem without pose-observed runs has no Occam term: its weight multiplies nothing)
    parts.append(np.array([wd[t] for t in TERMS], float))
    parts.append(prior_head(config.prior))
    parts.append(problem.effect_priors(config, scales.L))
    parts.append(np.asarray(s_ref, float))
    parts.append([config.solver.hessian_ridge if ridge is None else ridge])
    p = np.concatenate(parts)
    assert p.shape[0] == problem.n_p_total
    return p


def previous_trajectories(previous, dim: int, shape_name: str, runs: list) -> list:
    """Per run, the (T0, 3) [x, y m, angle rad] (2-D) or (T0, 7) [x, y, z m, qw, qx, qy,
    qz] (3-D) trajectory of an earlier estimate ``previous`` of the first T0 <= T
    samples of each run (a start from it: estimator.previous_start_2d,
    estimator3d.previous_start).  Raises TacestError (one line) where it does not fit:
    another dimension or shape parameterization, another number of runs, a trajectory
    longer than its run, of another width, or not finite."""
    if int(previous.dim) != int(dim) or previous.shape != shape_name:
        raise TacestError(f"the earlier estimate is a {previous.dim}-D {previous.shape}, not a {dim}-D {shape_name}")
    if len(previous.runs) != len(runs):
        raise TacestError(f"the earlier estimate has {len(previous.runs)} runs, these are {len(runs)}")
    width = 3 if int(dim) == 2 else 7
    out = []
    for run, re in zip(runs, previous.runs):
        P = np.asarray(re.pose, float)
        if P.ndim != 2 or P.shape[1] < width or not 0 < len(P) <= run.n_samples or not np.all(np.isfinite(P)):
            raise TacestError(f"the earlier estimate's trajectory ({P.shape}) does not fit a run of "
                              f"{run.n_samples} samples")
        out.append(P[:, :width])
    return out
