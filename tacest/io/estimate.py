"""Estimate files (``tacest.estimate``, SPEC v1): what ``tacest estimate`` found.

Shapes (K vertices, D = dim, T_i samples of run i, P pose size, V velocity size)::

    vertices            (K, D)   m, body frame (origin at the centre of mass)
    runs[i].pose        (T_i, P)
    runs[i].velocity    (T_i, V) [v (D), omega (1 or 3)], world frame
    runs[i].impulses    {contact name: (T_i, ...)} N·s, world frame
    runs[i].residuals   {term: (T_i,)} per-sample whitened squared residual of the term
    information         (n, n) observed information of the parameters, rows ``info_names``
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.io.h5util import Reader, atomic_h5, attr_str, open_h5
from tacest.io.run import pose_size, velocity_size

FORMAT = "tacest.estimate"
VERSION = 1

#: /params attrs that every estimate has (SPEC); others are effect parameters
CORE_PARAMS = ("mass", "inertia", "friction_ground", "friction_finger")


@dataclass
class RunEstimate:
    """Estimated trajectory of one input run."""

    pose: np.ndarray
    velocity: np.ndarray
    impulses: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    source_file: str = ""
    source_sha256: str = ""
    attrs: dict = field(default_factory=dict)


@dataclass
class Estimate:
    """The content of an estimate file.

    params : dict of name -> float or array (mass kg, inertia kg·m² (scalar in 2-D,
        (3, 3) in 3-D), friction_ground, friction_finger, effect parameters);
    model : list of effect names included in the model;
    identifiable : dict name -> bool, False where the data cannot tell the value
        (it is then the prior's);  std : dict name -> one-sigma uncertainty;
    fit_quality : the goodness-of-fit test of the residuals (tacest.estimation.fitquality:
        ``consistent``, ``worst`` windows, flagged ``terms``, ...), or None (an estimate
        written by another program, or before the test existed).
    """

    dim: int
    shape: str
    vertices: np.ndarray
    params: dict
    runs: list
    model: list = field(default_factory=list)
    solver_status: str = "unknown"
    success: bool = False
    iterations: int = 0
    wall_time: float = 0.0
    objective: float = float("nan")
    information: Optional[np.ndarray] = None
    info_names: list = field(default_factory=list)
    std: dict = field(default_factory=dict)
    identifiable: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    method: str = "implicit"
    filename: Optional[str] = None
    extra_attrs: dict = field(default_factory=dict)
    fit_quality: Optional[dict] = None

    @property
    def consistent(self) -> Optional[bool]:
        """True / False: the fit passed / failed its goodness-of-fit test; None: untested."""
        return None if self.fit_quality is None else bool(self.fit_quality.get("consistent"))


def write_estimate(est: Estimate, path) -> None:
    """Write an estimate file atomically."""
    with atomic_h5(path) as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        f.attrs["dim"] = int(est.dim)
        f.attrs["shape"] = est.shape
        f.attrs["model"] = json.dumps(list(est.model))
        f.attrs["method"] = est.method
        f.attrs["solver_status"] = str(est.solver_status)
        f.attrs["success"] = bool(est.success)
        f.attrs["iterations"] = int(est.iterations)
        f.attrs["wall_time"] = float(est.wall_time)
        f.attrs["objective"] = float(est.objective)
        f.attrs["config"] = json.dumps(est.config, sort_keys=True, default=_jsonable)
        for k, v in est.extra_attrs.items():
            f.attrs[k] = v
        if est.fit_quality is not None:
            f.attrs["fit_consistent"] = "yes" if est.fit_quality.get("consistent") else "no"
            f.attrs["fit_quality"] = json.dumps(est.fit_quality, default=_jsonable)
        g = f.create_group("params")
        g.create_dataset("vertices", data=np.asarray(est.vertices, float))
        for k, v in est.params.items():
            g.attrs[k] = np.asarray(v, float) if np.ndim(v) else float(v)
        # strict JSON: an unbounded sigma (a direction the data do not inform) is null
        g.attrs["std"] = json.dumps({k: (_jsonable(v) if np.isfinite(v) else None) for k, v in est.std.items()})
        g.attrs["identifiable"] = json.dumps({k: bool(v) for k, v in est.identifiable.items()})
        runs = f.create_group("runs")
        for i, r in enumerate(est.runs):
            rg = runs.create_group(str(i))
            rg.create_dataset("pose", data=np.asarray(r.pose, float))
            rg.create_dataset("velocity", data=np.asarray(r.velocity, float))
            ig = rg.create_group("impulses")
            for name, arr in r.impulses.items():
                ig.create_dataset(name, data=np.asarray(arr, float))
            resg = rg.create_group("residuals")
            for name, arr in r.residuals.items():
                resg.create_dataset(name, data=np.asarray(arr, float))
            rg.attrs["source_file"] = str(r.source_file)
            rg.attrs["source_sha256"] = str(r.source_sha256)
            for k, v in r.attrs.items():
                rg.attrs[k] = v
        if est.information is not None:
            ig = f.create_group("information")
            ig.create_dataset("observed", data=np.asarray(est.information, float))
            ig.create_dataset("names", data=np.array([str(n) for n in est.info_names], dtype=object))


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def read_estimate(path) -> Estimate:
    """Read and validate an estimate file (one clear error naming file and path)."""
    with open_h5(path) as f:
        r = Reader(f, path)
        fmt = attr_str(r.attr("/", "format"))
        if fmt != FORMAT:
            r.fail("attrs format", f"expected {FORMAT!r}, got {fmt!r}")
        version = int(np.asarray(r.attr("/", "version")).reshape(()))
        if version != VERSION:
            r.fail("attrs version", f"unknown version {version}")
        dim = int(np.asarray(r.attr("/", "dim")).reshape(()))
        if dim not in (2, 3):
            r.fail("attrs dim", f"must be 2 or 3, got {dim}")
        shape = attr_str(r.attr("/", "shape", "polygon"))
        try:
            model = json.loads(attr_str(r.attr("/", "model", "[]")))
        except json.JSONDecodeError:
            r.fail("attrs model", "not a JSON list")
        vertices = r.dataset("/params/vertices", (None, dim))
        params = {}
        pattrs = f["/params"].attrs
        for k in pattrs:
            if k in ("std", "identifiable"):
                continue
            v = np.asarray(pattrs[k], float)
            params[k] = float(v) if v.ndim == 0 else v
        for k in CORE_PARAMS:
            if k not in params:
                r.fail(f"/params attrs {k}", "required attribute is missing")
        std = {k: (float("inf") if v is None else v) for k, v in json.loads(attr_str(pattrs.get("std", "{}"))).items()}
        identifiable = json.loads(attr_str(pattrs.get("identifiable", "{}")))
        runs = []
        if "runs" not in f:
            r.fail("/runs", "required group is missing")
        P, V = pose_size(dim), velocity_size(dim)
        for key in sorted(f["runs"].keys(), key=lambda s: int(s) if s.isdigit() else s):
            base = f"/runs/{key}"
            pose = r.dataset(f"{base}/pose", (None, P))
            vel = r.dataset(f"{base}/velocity", (pose.shape[0], V))
            imp = {n: np.asarray(d[()]) for n, d in f[f"{base}/impulses"].items()} if f"{base}/impulses" in f else {}
            res = {n: np.asarray(d[()]) for n, d in f[f"{base}/residuals"].items()} if f"{base}/residuals" in f else {}
            ra = f[base].attrs
            runs.append(RunEstimate(pose=pose, velocity=vel, impulses=imp, residuals=res,
                                    source_file=attr_str(ra.get("source_file", "")),
                                    source_sha256=attr_str(ra.get("source_sha256", "")),
                                    attrs={k: ra[k] for k in ra if k not in ("source_file", "source_sha256")}))
        info, names = None, []
        if "information" in f:
            names = [attr_str(n) for n in f["information/names"][()]]
            info = r.dataset("/information/observed", (len(names), len(names)), allow_nan=True)
        a = f.attrs
        fit_quality = None
        if "fit_quality" in a:
            try:
                fit_quality = json.loads(attr_str(a["fit_quality"]))
            except json.JSONDecodeError:
                r.fail("attrs fit_quality", "not JSON")
            if not isinstance(fit_quality, dict) or not isinstance(fit_quality.get("consistent"), bool):
                r.fail("attrs fit_quality", "expected a JSON object with a boolean 'consistent'")
        est = Estimate(
            dim=dim, shape=shape, vertices=vertices, params=params, runs=runs, model=model,
            solver_status=attr_str(a.get("solver_status", "unknown")),
            success=bool(a.get("success", False)), iterations=int(a.get("iterations", 0)),
            wall_time=float(a.get("wall_time", 0.0)), objective=float(a.get("objective", np.nan)),
            information=info, info_names=names, std=std, identifiable=identifiable,
            config=json.loads(attr_str(a.get("config", "{}"))), method=attr_str(a.get("method", "implicit")),
            filename=str(path), fit_quality=fit_quality,
        )
    return est
