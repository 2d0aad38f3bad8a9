"""Cut runs (and estimated trajectories) into pieces for held-out comparisons.

A run with one long recording has no "other runs" to hold out, so the diagnosis splits
it at its action (poke) boundaries (``/actions/segments``) into sub-runs.  Every stream
is kept, the segments are re-based to the sub-run, and ``/truth`` (when present) is
sliced too.  A sub-run is a valid run of its own (:meth:`Run.validate`).

Note on sample 0: the estimator models sample 0 of every run as "at rest" (the
``rest`` residual in ``tacest.estimation.problem._start_function``).  The simulator
waits for the object to come to rest after every poke (``tacest.sim.record``,
REST_WAIT), so a cut at a poke boundary starts at rest, like a whole run; a cut in the
middle of a motion would not (the rest prior would then be wrong for that sub-run).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tacest.errors import TacestError
from tacest.io.estimate import RunEstimate
from tacest.io.run import Actions, Run, Truth

#: a sub-run needs at least this many samples (the estimator's minimum is 3; a poke
#: shorter than this carries no usable contact)
MIN_SUBRUN_SAMPLES = 10


def slice_run(run: Run, start: int, stop: int) -> Run:
    """The samples [start, stop) of ``run`` as a run of its own.

    Time keeps its absolute values (it only has to increase uniformly); actions that
    overlap the range are kept, clipped to it and re-based to start at 0.
    Raises TacestError for an empty or out-of-range slice.
    """
    T = run.n_samples
    start, stop = int(start), int(stop)
    if not (0 <= start < stop <= T) or stop - start < 3:
        raise TacestError(f"{run.filename or 'run'}: cannot cut samples [{start}, {stop}) "
                          f"from a run of {T} samples (need 0 <= start, start + 3 <= stop <= {T})")

    actions = None
    if run.actions is not None:
        seg = np.asarray(run.actions.segments, np.int64).reshape(-1, 2)
        keep = (seg[:, 1] > start) & (seg[:, 0] < stop)
        new_seg = np.clip(seg[keep], start, stop) - start
        params = np.asarray(run.actions.params, float)[keep]
        actions = Actions(segments=new_seg.astype(np.int64), params=params, kind=run.actions.kind,
                          names=list(run.actions.names))
    truth = None
    if run.truth is not None:
        tr = run.truth
        truth = Truth(pose=np.asarray(tr.pose)[start:stop].copy(), vertices=tr.vertices, mass=tr.mass,
                      inertia=tr.inertia, friction_ground=tr.friction_ground,
                      friction_finger=tr.friction_finger, effects=tr.effects)
    prior = dict(run.prior)
    if start > 0:
        prior.pop("initial_pose", None)  # it describes sample 0 of the whole run
    streams = {name: np.asarray(getattr(run, name))[start:stop].copy() for name in per_sample_fields(run)}
    return dataclasses.replace(run, **streams, actions=actions, truth=truth, prior=prior,
                               extra_attrs={**run.extra_attrs, "slice_start": start, "slice_stop": stop})


#: Run fields that are arrays but not per-sample streams
NOT_PER_SAMPLE = ("gravity", "finger_radius", "ground_normal")


def per_sample_fields(run: Run) -> list:
    """Names of the Run fields that hold one row per sample (time, robot, tactile,
    observations, quality masks, ...): every array field whose first axis is T, so that
    streams added to the run format later are cut along with the others."""
    T = run.n_samples
    names = []
    for f in dataclasses.fields(run):
        v = getattr(run, f.name)
        if f.name in NOT_PER_SAMPLE or not isinstance(v, np.ndarray):
            continue
        if v.ndim >= 1 and v.shape[0] == T:
            names.append(f.name)
    return names


def action_ranges(run: Run, min_samples: int = MIN_SUBRUN_SAMPLES) -> list:
    """[(start, stop), ...] sample ranges that tile the run, one per action.

    The first range starts at 0 and the last ends at T; samples between two actions go
    to the earlier one.  Actions shorter than ``min_samples`` are merged into their
    neighbour.  A run without actions is one range.
    """
    T = run.n_samples
    if run.actions is None or len(run.actions.segments) == 0:
        return [(0, T)]
    starts = sorted({int(s) for s in np.asarray(run.actions.segments)[:, 0]} | {0})
    starts = [s for s in starts if 0 <= s < T]
    bounds = starts + [T]
    ranges = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    merged = []
    for a, b in ranges:
        if merged and (b - a < min_samples or merged[-1][1] - merged[-1][0] < min_samples):
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    return merged


def split_at_actions(run: Run, min_samples: int = MIN_SUBRUN_SAMPLES) -> list:
    """The run cut into sub-runs at its action boundaries (see :func:`action_ranges`)."""
    return [slice_run(run, a, b) for a, b in action_ranges(run, min_samples)]


def join_runs(parts: list) -> Run:
    """Inverse of :func:`split_at_actions` for consecutive slices of one run: the
    sub-runs concatenated in order (streams, truth poses and re-based actions)."""
    if not parts:
        raise TacestError("no runs to join")
    first = parts[0]

    segs, params, off = [], [], 0
    for p in parts:
        if p.actions is not None:
            segs.append(np.asarray(p.actions.segments) + off)
            params.append(np.asarray(p.actions.params))
        off += p.n_samples
    actions = None
    if first.actions is not None:
        actions = Actions(segments=np.concatenate(segs).astype(np.int64), params=np.concatenate(params),
                          kind=first.actions.kind, names=list(first.actions.names))
    truth = None
    if all(p.truth is not None for p in parts):
        tr = first.truth
        truth = dataclasses.replace(tr, pose=np.concatenate([p.truth.pose for p in parts]))
    extra = {k: v for k, v in first.extra_attrs.items() if k not in ("slice_start", "slice_stop")}
    names = set(per_sample_fields(first))
    for p in parts[1:]:
        if set(per_sample_fields(p)) != names:
            raise TacestError("cannot join runs with different streams")
    streams = {name: np.concatenate([np.asarray(getattr(p, name)) for p in parts]) for name in names}
    return dataclasses.replace(first, **streams, actions=actions, truth=truth, extra_attrs=extra)


def slice_run_estimate(re: RunEstimate, start: int, stop: int) -> RunEstimate:
    """Samples [start, stop) of an estimated trajectory (pose, velocity, impulses,
    residuals).  The impulses at the new sample 0 (an interval outside the slice) are
    zeroed, as the estimator writes them for a run's first sample."""
    imp = {}
    for k, v in re.impulses.items():
        a = np.asarray(v)[start:stop].copy()
        a[0] = 0.0
        imp[k] = a
    res = {k: np.asarray(v)[start:stop].copy() for k, v in re.residuals.items()}
    return RunEstimate(pose=np.asarray(re.pose)[start:stop].copy(), velocity=np.asarray(re.velocity)[start:stop].copy(),
                       impulses=imp, residuals=res, source_file=re.source_file, source_sha256=re.source_sha256,
                       attrs={**re.attrs, "slice_start": int(start), "slice_stop": int(stop)})
