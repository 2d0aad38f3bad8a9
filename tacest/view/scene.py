"""What ``tacest view`` draws, gathered from a run file, an estimate file, or both.

:func:`load_scene` reads FILE (a run or an estimate, told apart by its ``format``
attr) and, for an estimate, the run it came from (``--run``, else the estimate's
``source_file`` when that file exists and has as many samples), and returns a
:class:`Scene`: the true shape and trajectory (a simulated run's /truth), the estimated
shape and trajectory, the fingertips, contacts and normals, all in SPEC's world frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import h5py
import numpy as np

from tacest.errors import TacestError

log = logging.getLogger(__name__)

#: s, sample period assumed for an estimate shown without its run file (SPEC runs
#: recorded by tacest are 100 Hz by default); the frames then say "sample k"
ASSUMED_DT = 0.01


@dataclass
class Scene:
    """T samples, F fingers, D = dim, P pose size.

    time : (T,) s; est_vertices (K, D) / est_pose (T, P) or None; true_vertices (K', D) /
    true_pose (T, P) or None; finger_position (T, F, D) m, finger_radius (F,) m,
    contact (T, F) bool, normal (T, F, D) (NaN off contact), or None without fingers;
    title : what is shown.
    """

    dim: int
    time: np.ndarray
    est_vertices: Optional[np.ndarray] = None
    est_pose: Optional[np.ndarray] = None
    true_vertices: Optional[np.ndarray] = None
    true_pose: Optional[np.ndarray] = None
    finger_position: Optional[np.ndarray] = None
    finger_radius: Optional[np.ndarray] = None
    contact: Optional[np.ndarray] = None
    normal: Optional[np.ndarray] = None
    title: str = ""
    #: False when no run file gave the sample times (they are then sample indices x 0.01 s)
    time_known: bool = True

    @property
    def n_samples(self) -> int:
        return int(len(self.time))


def file_format(path) -> str:
    """``tacest.run`` or ``tacest.estimate`` (a TacestError naming the file otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise TacestError(f"{path}: no such file")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format", "")
    except OSError:
        raise TacestError(f"{path}: not an HDF5 file (expected a run or an estimate file)") from None
    fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
    if fmt not in ("tacest.run", "tacest.estimate"):
        raise TacestError(f"{path}: attrs format: {fmt!r} is neither a run nor an estimate file")
    return fmt


def _source_run(est, est_path, run_index):
    from tacest.io.run import read_run

    src = est.runs[run_index].source_file
    if not src:
        return None
    for cand in (Path(src), Path(est_path).parent / Path(src).name):
        if cand.is_file():
            try:
                run = read_run(cand)
            except TacestError:
                continue
            if run.n_samples == len(est.runs[run_index].pose):
                log.info("finger path from %s (the estimate's source file)", cand)
                return run
    return None


def load_scene(path, run_path=None, run_index: int = 0) -> Scene:
    """The Scene of FILE ``path`` (module docstring)."""
    from tacest.io.estimate import read_estimate
    from tacest.io.run import read_run

    fmt = file_format(path)
    est = run = None
    if fmt == "tacest.run":
        if run_path:
            raise TacestError(f"{path}: is a run file; --run is for an estimate")
        run = read_run(path)
    else:
        est = read_estimate(path)
        if not est.runs:
            raise TacestError(f"{path}: /runs: the estimate has no trajectory to show")
        if not 0 <= run_index < len(est.runs):
            raise TacestError(f"{path}: /runs/{run_index}: no such run (the estimate has {len(est.runs)})")
        if run_path:
            run = read_run(run_path)
            if run.n_samples != len(est.runs[run_index].pose):
                raise TacestError(f"{run_path}: /time has {run.n_samples} samples, {path} /runs/{run_index}/pose "
                                  f"{len(est.runs[run_index].pose)}: not the run of this estimate")
        else:
            run = _source_run(est, path, run_index)
        if run is not None and run.dim != est.dim:
            raise TacestError(f"{run_path or path}: a {run.dim}-D run for a {est.dim}-D estimate")
    dim = est.dim if est is not None else run.dim
    if est is not None:
        T = len(est.runs[run_index].pose)
        time = run.time if run is not None else np.arange(T) * ASSUMED_DT
    else:
        time = run.time
    sc = Scene(dim=dim, time=np.asarray(time, float), time_known=run is not None)
    if est is not None:
        sc.est_vertices = np.asarray(est.vertices, float)
        sc.est_pose = np.asarray(est.runs[run_index].pose, float)
    if run is not None:
        if run.truth is not None:
            sc.true_vertices = np.asarray(run.truth.vertices, float)
            sc.true_pose = np.asarray(run.truth.pose, float)
        if run.finger_position is not None:
            sc.finger_position = np.asarray(run.finger_position, float)
            sc.finger_radius = np.asarray(run.finger_radius, float)
            sc.contact = np.asarray(run.contact).astype(bool)
            sc.normal = np.asarray(run.normal, float)
    parts = []
    if sc.true_pose is not None:
        parts.append("true shape")
    if sc.est_pose is not None:
        parts.append("estimated shape")
    if sc.finger_position is not None:
        parts.append("fingers, contacts, normals")
    if not parts:
        raise TacestError(f"{path}: nothing to show: no /truth, no estimate and no fingers")
    sc.title = f"{Path(path).name}: " + ", ".join(parts)
    return sc


def frame_indices(n_samples: int, dt: float, fps: float, max_frames: int) -> np.ndarray:
    """Sample indices shown as frames: real time at ``fps`` (one frame every
    round(1 / (fps dt)) samples), thinned further to at most ``max_frames``; the last
    sample always included."""
    stride = max(1, int(round(1.0 / (fps * dt))))
    stride = max(stride, int(np.ceil(n_samples / max(1, max_frames))))
    idx = np.arange(0, n_samples, stride)
    if idx[-1] != n_samples - 1:
        idx = np.append(idx, n_samples - 1)
    if len(idx) > max_frames:
        idx = np.unique(np.round(np.linspace(0, n_samples - 1, max_frames)).astype(int))
    return idx
