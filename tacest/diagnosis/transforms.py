"""Sensor-timing candidates as data transforms: they need no change to the NLP.

- ``latency`` (tactile streams k whole samples late): :func:`undo_latency` advances the
  contact, force and normal streams by k samples, so that the tactile reading of
  interval k+t is paired with the fingertip position of sample t.  The last k samples,
  whose readings were never recorded, repeat the last reading (edge padding: the run
  keeps its length, so objectives of different k are sums over the same samples; at the
  end of a recording the finger holds still).
- ``time_scale`` (the recorder's clock runs at ``scale`` × the true rate):
  :func:`undo_time_scale` divides ``dt`` and ``/time`` by the scale.  Positions, forces
  and sample counts are left as they are: this inverts the clock error exactly (SPEC
  "clock or length scale off"; a length error would instead rescale positions, which
  through gravity is not the same model).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tacest.errors import TacestError
from tacest.io.run import Run


#: Run fields delayed by a tactile latency (SPEC: contact, force, normal) and the quality
#: masks of the tactile readings
TACTILE_FIELDS = ("contact", "force", "normal", "missing", "missing_finger")


def undo_latency(run: Run, k: int) -> Run:
    """The run with its tactile streams advanced by ``k`` >= 0 samples (see module doc)."""
    k = int(k)
    if k < 0:
        raise TacestError(f"latency must be >= 0 samples, got {k}")
    if k == 0 or run.contact is None:
        return run
    T = run.n_samples
    if k >= T:
        raise TacestError(f"{run.filename or 'run'}: latency {k} is not shorter than the run ({T} samples)")

    def advance(a):
        if a is None:
            return None
        a = np.asarray(a)
        return np.concatenate([a[k:], np.repeat(a[-1:], k, axis=0)])

    # the tactile streams, and the masks of readings that never arrived, which move with them
    changes = {name: advance(getattr(run, name)) for name in TACTILE_FIELDS if getattr(run, name, None) is not None}
    changes["contact"] = changes["contact"].astype(np.uint8)
    return dataclasses.replace(run, **changes)


def undo_time_scale(run: Run, scale: float) -> Run:
    """The run with its clock corrected: ``dt`` and ``/time`` divided by ``scale`` (> 0)."""
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise TacestError(f"time scale must be > 0, got {scale}")
    if scale == 1.0:
        return run
    return dataclasses.replace(run, dt=run.dt / scale, time=np.asarray(run.time, float) / scale)


def apply_transform(run: Run, name: str, value) -> Run:
    """``undo_<name>`` of the run for a transform candidate; identity for ``none``."""
    if name == "latency":
        return undo_latency(run, int(value))
    if name == "time_scale":
        return undo_time_scale(run, float(value))
    if name == "none":
        return run
    raise TacestError(f"effect {name!r} is not a data transform")
