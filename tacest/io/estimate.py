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
from tacest.io.run import MAX_ABS_POSITION, check_plausible, pose_size, velocity_size
from tacest.provenance import provenance

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

    @property
    def local_misfit(self) -> bool:
        """Consistent, but some windows were flagged locally (fit_quality.local_misfit)."""
        return bool(self.consistent and self.fit_quality.get("local_misfit"))


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
        f.attrs.update(provenance())
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


def _json_attr(r: Reader, where: str, raw, kind):
    """A JSON attr that must decode to ``kind`` (dict or list)."""
    try:
        value = json.loads(attr_str(raw))
    except (json.JSONDecodeError, UnicodeDecodeError):
        r.fail(where, "not valid JSON")
    if not isinstance(value, kind):
        r.fail(where, f"expected a JSON {'object' if kind is dict else 'list'}, got {type(value).__name__}")
    return value


def _group(r: Reader, h5path):
    import h5py

    obj = r.f.get(h5path)
    if obj is None:
        r.fail(h5path, "required group is missing")
    if not isinstance(obj, h5py.Group):
        r.fail(h5path, "expected a group, found a dataset")
    return obj


def _param(r: Reader, name, raw, dim):
    """One /params attr as a float or an array; core parameters must be physical (a
    friction may be NaN: not estimated)."""
    where = f"/params attrs {name}"
    try:
        v = np.asarray(raw, float)
    except (TypeError, ValueError):
        r.fail(where, f"expected a number, got {raw!r}")
    if name.startswith("friction_") and v.size == 1 and np.isnan(v).all():
        return float("nan")  # not estimated (another program's estimate): evaluation reports n/a
    if not np.all(np.isfinite(v)):
        r.fail(where, "must be finite")
    if name == "inertia" and dim == 3:
        if v.size != 9:
            r.fail(where, f"expected a (3, 3) matrix in 3-D, got shape {v.shape}")
        v = v.reshape(3, 3)
    elif name in CORE_PARAMS and v.size != 1:
        r.fail(where, f"expected a number, got shape {v.shape}")
    if name in ("mass", "inertia") and v.size == 1 and not float(v.reshape(())) > 0:
        r.fail(where, f"must be > 0, got {float(v.reshape(()))}")
    if name.startswith("friction_") and v.size == 1 and not float(v.reshape(())) >= 0:
        r.fail(where, f"must be >= 0, got {float(v.reshape(()))}")
    return float(v.reshape(())) if v.size == 1 and v.ndim <= 1 else v


def read_estimate(path) -> Estimate:
    """Read and validate an estimate file (one clear error naming file and path;
    docs/formats.md, "Validation of estimate files")."""
    import h5py

    with open_h5(path) as f:
        r = Reader(f, path)
        fmt = attr_str(r.attr("/", "format"))
        if fmt != FORMAT:
            r.fail("attrs format", f"expected {FORMAT!r}, got {fmt!r}")
        version = r.attr_int("/", "version")
        if version != VERSION:
            r.fail("attrs version", f"unknown version {version} (this tacest reads version {VERSION})")
        dim = r.attr_int("/", "dim")
        if dim not in (2, 3):
            r.fail("attrs dim", f"must be 2 or 3, got {dim}")
        shape = attr_str(r.attr("/", "shape", "polygon"))
        _check_shape_name(r, shape, dim)
        model = _json_attr(r, "attrs model", r.attr("/", "model", "[]"), list)
        pgroup = _group(r, "/params")
        vertices = r.dataset("/params/vertices", (None, dim))
        check_plausible(path, "/params/vertices", vertices, MAX_ABS_POSITION, "m", "MAX_ABS_POSITION")
        if vertices.shape[0] < dim + 1:
            r.fail("/params/vertices", f"a {dim}-D shape needs at least {dim + 1} vertices, got {vertices.shape[0]}")
        params = {}
        pattrs = pgroup.attrs
        for k in pattrs:
            if k in ("std", "identifiable"):
                continue
            params[k] = _param(r, k, pattrs[k], dim)
        for k in CORE_PARAMS:
            if k not in params:
                r.fail(f"/params attrs {k}", "required attribute is missing")
        std = {}
        for k, v in _json_attr(r, "/params attrs std", pattrs.get("std", "{}"), dict).items():
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                r.fail("/params attrs std", f"{k}: expected a number or null, got {v!r}")
            std[k] = float("inf") if v is None else float(v)
        identifiable = _json_attr(r, "/params attrs identifiable", pattrs.get("identifiable", "{}"), dict)
        runs_group = _group(r, "/runs")
        keys = list(runs_group.keys())
        if not keys:
            r.fail("/runs", "holds no run")
        if sorted(keys, key=lambda s: (len(s), s)) != [str(i) for i in range(len(keys))]:
            r.fail("/runs", f"run groups must be named 0 .. {len(keys) - 1}, got {', '.join(sorted(keys)[:5])}")
        P, V = pose_size(dim), velocity_size(dim)
        runs = []
        for i in range(len(keys)):
            base = f"/runs/{i}"
            rg = _group(r, base)
            pose = r.dataset(f"{base}/pose", (None, P))
            check_plausible(path, f"{base}/pose", pose[:, :dim], MAX_ABS_POSITION, "m", "MAX_ABS_POSITION")
            T = pose.shape[0]
            if T < 2:
                r.fail(f"{base}/pose", f"needs at least 2 samples, got {T}")
            vel = r.dataset(f"{base}/velocity", (T, V))
            arrays = {}
            for part in ("impulses", "residuals"):
                arrays[part] = {}
                if f"{base}/{part}" not in f:
                    continue
                for n, d in _group(r, f"{base}/{part}").items():
                    where = f"{base}/{part}/{n}"
                    if not isinstance(d, h5py.Dataset):
                        r.fail(where, "expected a dataset, found a group")
                    want = (T,) if part == "residuals" else (T,) + (None,) * max(len(d.shape) - 1, 1)
                    arrays[part][n] = r.dataset(where, want)
            ra = rg.attrs
            sha = attr_str(ra.get("source_sha256", ""))
            if sha and not (len(sha) == 64 and all(c in "0123456789abcdef" for c in sha)):
                r.fail(f"{base} attrs source_sha256", f"expected 64 hex digits, got {sha[:80]!r}")
            runs.append(RunEstimate(pose=pose, velocity=vel, impulses=arrays["impulses"],
                                    residuals=arrays["residuals"],
                                    source_file=attr_str(ra.get("source_file", "")), source_sha256=sha,
                                    attrs={k: ra[k] for k in ra if k not in ("source_file", "source_sha256")}))
        info, names = None, []
        if "information" in f:
            _group(r, "/information")
            if "/information/names" not in f:
                r.fail("/information/names", "required dataset is missing")
            raw_names = f["/information/names"]
            if not isinstance(raw_names, h5py.Dataset) or raw_names.ndim != 1:
                r.fail("/information/names", "expected a list of names (n,)")
            try:
                names = [attr_str(n) for n in raw_names[()]]
            except (TypeError, ValueError, UnicodeDecodeError):
                r.fail("/information/names", "expected strings")
            info = r.dataset("/information/observed", (len(names), len(names)), allow_nan=True)
        fit_quality = None
        if "fit_quality" in f.attrs:
            fit_quality = _json_attr(r, "attrs fit_quality", f.attrs["fit_quality"], dict)
            if not isinstance(fit_quality.get("consistent"), bool):
                r.fail("attrs fit_quality", "expected a JSON object with a boolean 'consistent'")
        extra = {}
        if "sensor_noise" in f.attrs:  # the sensors' noise that judged the fit (docs/formats.md)
            noise = _json_attr(r, "attrs sensor_noise", f.attrs["sensor_noise"], dict)
            for k, v in noise.items():
                ok = isinstance(v, dict) and isinstance(v.get("setting"), str) and v["setting"].startswith("noise.") \
                    and all(isinstance(v.get(n), (int, float)) and not isinstance(v.get(n), bool)
                            and np.isfinite(v[n]) and v[n] > 0 for n in ("configured", "used"))
                if not ok:
                    r.fail("attrs sensor_noise", f"{k}: expected setting, configured and used (> 0), got {v!r}")
            extra["sensor_noise"] = json.dumps(noise)
        success = r.attr("/", "success", False)
        if np.asarray(success).shape != () or np.asarray(success).dtype.kind not in "biu":
            r.fail("attrs success", f"expected true or false, got {success!r}")
        est = Estimate(
            dim=dim, shape=shape, vertices=vertices, params=params, runs=runs, model=model,
            solver_status=attr_str(r.attr("/", "solver_status", "unknown")),
            success=bool(success), iterations=r.attr_int("/", "iterations", 0),
            wall_time=r.attr_float("/", "wall_time", 0.0), objective=_objective(r),
            information=info, info_names=names, std=std, identifiable=identifiable,
            config=_json_attr(r, "attrs config", r.attr("/", "config", "{}"), dict),
            method=attr_str(r.attr("/", "method", "implicit")),
            filename=str(path), fit_quality=fit_quality, extra_attrs=extra,
        )
    return est


def _check_shape_name(r: Reader, shape: str, dim: int) -> None:
    from tacest.errors import TacestError

    try:
        if dim == 2:
            from tacest.geometry.shapes import make_shape

            make_shape(shape)
        else:
            from tacest.geometry.shapes3d import make_shape_3d

            make_shape_3d(shape)
    except TacestError as exc:
        r.fail("attrs shape", str(exc))


def _objective(r: Reader) -> float:
    raw = r.attr("/", "objective", float("nan"))
    try:
        return float(np.asarray(raw, float).reshape(()))
    except (TypeError, ValueError):
        r.fail("attrs objective", f"expected a number, got {raw!r}")


def check_runs_match(est: Estimate, run_paths) -> None:
    """TacestError unless ``run_paths`` are the run files ``est`` was estimated from, in
    order: as many, and each with the SHA-256 its ``/runs/<i>`` attrs ``source_sha256``
    records (a run without a recorded checksum, from another program, is not checked)."""
    from tacest.errors import TacestError
    from tacest.io.h5util import sha256_file

    where = est.filename or "estimate"
    run_paths = list(run_paths)
    if len(run_paths) != len(est.runs):
        raise TacestError(f"{where}: was estimated from {len(est.runs)} run(s), {len(run_paths)} given; "
                          "give the runs it was estimated from, in order")
    recorded = [re.source_sha256 for re in est.runs]
    for i, path in enumerate(run_paths):
        if not recorded[i]:
            continue
        sha = sha256_file(path)
        if sha == recorded[i]:
            continue
        hint = (f"it is run {recorded.index(sha)} of the estimate; give the runs in order" if sha in recorded else
                "it is not a run the estimate was made from (another object, or the run changed since)")
        raise TacestError(f"{path}: SHA-256 {sha[:12]}... differs from {where} /runs/{i} attrs source_sha256 "
                          f"{recorded[i][:12]}...; {hint}")
