"""Runs recorded faster than the estimator needs, fitted at a coarser sample period.

SPEC allows any uniform sample period.  The estimator's NLP has variables per sample, and
its time grows faster than linearly with their number: a 10 s run at 500 Hz (a MuJoCo
world's default step) holds five times the samples of the same run at 100 Hz, which the
estimator fits just as well (tacest's own recordings are 100 Hz).  So a run whose period
is well below ``solver.sample_period`` is fitted on blocks of k consecutive samples
(:func:`coarsen_run`), and the estimated trajectory is brought back to every sample of
the run (:func:`refine_run_estimate`): the estimate file has one row per sample of the
run file, as SPEC says.

Block 0 is the run's sample 0 alone (so a run that starts at rest still does); block
j >= 1 holds samples ((j - 1)·k, j·k]; the up to k - 1 samples after the last whole block
are not fitted (the trajectory holds its last fitted pose there, with no impulses).  Each coarse sample
stands at its block's last sample, so that, as at the run's own rate, a sample describes
the interval that ends at it:

- time, fingertip positions, pose observations: the block's last sample (a missing
  fingertip there: missing);
- contact: 1 if the finger touched at any sample of the block;
- force: the mean over the block (a force reading is impulse / dt: the block's mean is
  its total impulse over the block's duration);
- normal: the mean of the block's measured normals, normalised (NaN where none);
- actions: their segments in blocks (a segment covers every block it touches);
- truth (for evaluation only): the poses at the blocks' last samples.

The attr ``fitted_every`` of the estimate (JSON list, k per run) says where this was
done; ``solver.sample_period = 0`` turns it off.  Only ``tacest estimate`` (and the
commands built on tacest.dims.estimate_runs: demo, batch, explore) coarsen; the diagnosis
fits every run at its own rate.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from tacest.io.estimate import RunEstimate
from tacest.io.run import Actions, Run, Truth


def coarsening_factor(dt: float, period: float) -> int:
    """k: the most samples of period ``dt`` whose block lasts at most ``period`` (1: none,
    for any dt above half the period; ``period`` <= 0: off)."""
    if not period > 0 or not dt > 0:
        return 1
    return max(1, int(math.floor(period / dt * (1 + 1e-9))))


def block_ends(T: int, k: int) -> np.ndarray:
    """(T',) indices of the samples the coarse samples stand at: 0, then the last
    sample of each whole block of k after it (uniform in time, as SPEC wants; the up to
    k - 1 samples after the last whole block are not fitted)."""
    return np.arange(0, T, k, dtype=np.int64)


def coarsen_run(run: Run, k: int) -> Run:
    """``run`` at k times its sample period (module doc); the run itself for k = 1."""
    if k <= 1:
        return run
    T = run.n_samples
    ends = block_ends(T, k)
    starts = np.concatenate([[0], ends[:-1] + 1])
    Tc = len(ends)
    fields = {"time": np.asarray(run.time, float)[ends], "dt": run.dt * k}
    if run.n_fingers:
        missing = run.finger_missing_mask  # (T, F)
        on = np.asarray(run.contact, bool) & ~missing
        contact = np.zeros((Tc, run.n_fingers), np.uint8)
        normal = np.full((Tc, run.n_fingers, run.dim), np.nan)
        force = None if run.force is None else np.zeros((Tc, run.n_fingers, run.dim))
        for j, (a, b) in enumerate(zip(starts, ends + 1)):
            block_on = on[a:b]  # (n, F)
            contact[j] = block_on.any(axis=0)
            for f in np.flatnonzero(contact[j]):
                n = np.asarray(run.normal[a:b, f], float)[block_on[:, f]]
                n = n[np.all(np.isfinite(n), axis=1)]
                if len(n):
                    m = n.mean(axis=0)
                    norm = np.linalg.norm(m)
                    normal[j, f] = m / norm if norm > 1e-9 else n[-1]
                else:
                    contact[j, f] = 0
            if force is not None:
                ok = ~missing[a:b]
                fb = np.asarray(run.force[a:b], float)
                for f in range(run.n_fingers):
                    force[j, f] = fb[ok[:, f], f].mean(axis=0) if ok[:, f].any() else fb[-1, f]
        fields.update(finger_position=np.asarray(run.finger_position, float)[ends], contact=contact, normal=normal,
                      force=force)
        if run.missing_finger is not None or run.missing is not None:
            mf = missing[ends].astype(np.uint8)
            fields.update(missing_finger=mf, missing=mf.any(axis=1).astype(np.uint8))
    if run.pose_obs is not None:
        fields["pose_obs"] = np.asarray(run.pose_obs, float)[ends]
    if run.actions is not None:
        seg = np.asarray(run.actions.segments, np.int64).reshape(-1, 2)
        # a sample index s lies in coarse sample searchsorted(ends, s) (block ends >= s)
        new = np.stack([np.searchsorted(ends, seg[:, 0]), np.searchsorted(ends, seg[:, 1] - 1) + 1], axis=1)
        new = np.minimum(new, Tc)
        keep = new[:, 0] < new[:, 1]  # an action within the unfitted tail has no block
        fields["actions"] = Actions(segments=new[keep].astype(np.int64),
                                    params=np.asarray(run.actions.params, float).reshape(len(seg), -1)[keep],
                                    kind=run.actions.kind, names=list(run.actions.names))
    if run.truth is not None:
        tr = run.truth
        fields["truth"] = Truth(pose=np.asarray(tr.pose, float)[ends], vertices=tr.vertices, mass=tr.mass,
                                inertia=tr.inertia, friction_ground=tr.friction_ground,
                                friction_finger=tr.friction_finger, effects=tr.effects)
    return dataclasses.replace(run, **fields, extra_attrs={**run.extra_attrs, "coarsened_by": int(k)})


def refine_run_estimate(re: RunEstimate, run: Run, k: int) -> RunEstimate:
    """The estimate ``re`` of ``coarsen_run(run, k)`` at every sample of ``run``: poses
    and velocities interpolated in time (positions and 2-D angles linearly, 3-D
    quaternions normalised after linear interpolation along the shorter arc), each
    coarse sample's impulses spread evenly over its block's samples (their sums
    kept), each coarse sample's residuals at its block's last sample (their sums kept;
    zero elsewhere)."""
    if k <= 1:
        return re
    T = run.n_samples
    ends = block_ends(T, k)
    starts = np.concatenate([[0], ends[:-1] + 1])
    t_c = np.asarray(run.time, float)[ends]
    t = np.asarray(run.time, float)

    def interp(a):
        a = np.asarray(a, float)
        return np.stack([np.interp(t, t_c, a[:, c]) for c in range(a.shape[1])], axis=1)

    pose = np.asarray(re.pose, float).copy()
    if run.dim == 3:  # quaternions on one hemisphere along the trajectory before interpolating
        q = pose[:, 3:7]
        for j in range(1, len(q)):
            if np.dot(q[j], q[j - 1]) < 0:
                q[j] = -q[j]
    fine_pose = interp(pose)
    if run.dim == 3:
        fine_pose[:, 3:7] /= np.linalg.norm(fine_pose[:, 3:7], axis=1, keepdims=True)
    covered = np.arange(T) <= ends[-1]  # the samples after the last whole block are not fitted
    block_of = np.minimum(np.searchsorted(ends, np.arange(T)), len(ends) - 1)  # each sample's coarse sample
    sizes = (ends - starts + 1).astype(float)
    impulses = {}
    for name, v in re.impulses.items():
        v = np.asarray(v, float)
        shape = (-1,) + (1,) * (v.ndim - 1)
        impulses[name] = v[block_of] / sizes[block_of].reshape(shape) * covered.reshape(shape)
    residuals = {}
    for name, v in re.residuals.items():
        r = np.zeros(T)
        r[ends] = np.asarray(v, float)
        residuals[name] = r
    return RunEstimate(pose=fine_pose, velocity=interp(re.velocity), impulses=impulses, residuals=residuals,
                       source_file=re.source_file, source_sha256=re.source_sha256,
                       attrs={**re.attrs, "fitted_every": int(k)})


def coarsen_run_estimate(re: RunEstimate, k: int) -> RunEstimate:
    """An estimate of a run's first samples at the run's own rate (an earlier estimate
    started from) at k times its sample period: poses and velocities at the blocks' last
    samples, impulses and residuals summed over each block (the inverse of
    :func:`refine_run_estimate` where that was applied)."""
    if k <= 1:
        return re
    T = len(np.asarray(re.pose))
    ends = block_ends(T, k)
    n = ends[-1] + 1  # the samples of whole blocks
    block_of = np.searchsorted(ends, np.arange(n))

    def summed(v):
        v = np.asarray(v, float)
        out = np.zeros((len(ends),) + v.shape[1:])
        np.add.at(out, block_of, v[:n])
        return out

    return RunEstimate(pose=np.asarray(re.pose, float)[ends], velocity=np.asarray(re.velocity, float)[ends],
                       impulses={n: summed(v) for n, v in re.impulses.items()},
                       residuals={n: summed(v) for n, v in re.residuals.items()},
                       source_file=re.source_file, source_sha256=re.source_sha256, attrs=dict(re.attrs))
