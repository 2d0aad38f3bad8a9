"""Plan files (``tacest.plan``, SPEC v1): the next action chosen by ``tacest plan``.

Layout (N candidate actions of n parameters each)::

    /candidates/params  (N, n)  float, every action that was scored (N may be 0)
    /candidates/score   (N,)    float, its score (larger is better)
    /chosen/params      (n,)    float, the action to execute
    attrs method          str   how candidates were searched (``eig``, ``random``, ...)
    attrs score           str   scalarization (``logdet``, ``A``, ``D``, ``E``)
    attrs estimate_sha256 str   SHA-256 of the estimate file it was planned from
                                ("" when the plan used none, e.g. a random plan)
    attrs runs_sha256     str   tacest extension, optional: JSON list of the SHA-256 of
                                the run files it was planned from, in order; the poke
                                continues the last of them (:func:`check_plan_continues`)

tacest extensions (docs/simulation.md, "Plan files"): attrs ``format`` = ``"tacest.plan"`` and
``version`` = 1 (optional on read, so plans written by other programs work), and on
``/chosen/params`` and ``/candidates/params`` the attrs ``kind`` (``"poke"``) and
``names`` (the n parameter names, as in a run file's /actions/params).  A plan
without ``names`` is read as poke parameters in the order of
:data:`tacest.sim.pokes.POKE_NAMES` when n matches.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.io.h5util import Reader, atomic_h5, attr_str, open_h5
from tacest.provenance import PROVENANCE_ATTRS, provenance

FORMAT = "tacest.plan"
VERSION = 1
#: root attr: JSON list of the SHA-256 of the run files a plan was made from (in order)
RUNS_SHA256 = "runs_sha256"
#: the parameter names of a poke action (defined here, at the file-format edge, and
#: re-exported by tacest.sim.pokes; docs/simulation.md explains each)
POKE_NAMES = ("finger", "approach_angle", "target_x", "target_y", "depth", "speed")


@dataclass
class Plan:
    """The content of a plan file.

    chosen : (n,) parameters of the action to execute; candidates : (N, n);
    scores : (N,); names : n parameter names; kind : action kind (``"poke"``);
    method, score : strings (SPEC); estimate_sha256 : hex string or "".
    """

    chosen: np.ndarray
    candidates: np.ndarray
    scores: np.ndarray
    method: str
    score: str
    estimate_sha256: str = ""
    names: list = field(default_factory=lambda: list(POKE_NAMES))
    kind: str = "poke"
    extra_attrs: dict = field(default_factory=dict)
    filename: Optional[str] = None

    @property
    def n_params(self) -> int:
        return int(np.asarray(self.chosen).shape[0])

    def chosen_dict(self) -> dict:
        """{name: value} of the chosen action."""
        return {str(n): float(v) for n, v in zip(self.names, np.asarray(self.chosen, float))}


def _validate(plan: Plan, filename):
    from tacest.errors import FileFormatError

    def fail(path, problem):
        raise FileFormatError(str(filename), path, problem)

    chosen = np.asarray(plan.chosen, float)
    if chosen.ndim != 1 or chosen.shape[0] < 1:
        fail("/chosen/params", f"expected shape (n,) with n >= 1, got {chosen.shape}")
    if not np.all(np.isfinite(chosen)):
        fail("/chosen/params", "contains NaN or inf")
    n = chosen.shape[0]
    cand = np.asarray(plan.candidates, float)
    if cand.ndim != 2 or cand.shape[1] != n:
        fail("/candidates/params", f"expected shape (N, {n}), got {cand.shape}")
    if not np.all(np.isfinite(cand)):
        fail("/candidates/params", "contains NaN or inf")
    sc = np.asarray(plan.scores, float)
    if sc.shape != (cand.shape[0],):
        fail("/candidates/score", f"expected shape ({cand.shape[0]},), got {sc.shape}")
    if np.any(np.isnan(sc)):
        fail("/candidates/score", "contains NaN")
    if len(plan.names) != n:
        fail("/chosen/params attrs names", f"expected {n} names, got {len(plan.names)}")
    for name in ("method", "score"):
        if not str(getattr(plan, name)):
            fail(f"attrs {name}", "must be a non-empty string")
    if plan.estimate_sha256 and not _is_sha256(plan.estimate_sha256):
        fail("attrs estimate_sha256", f"expected 64 hex digits or \"\", got {str(plan.estimate_sha256)[:80]!r}")
    if RUNS_SHA256 in plan.extra_attrs:
        try:
            shas = json.loads(attr_str(plan.extra_attrs[RUNS_SHA256]))
        except (json.JSONDecodeError, UnicodeDecodeError):
            fail(f"attrs {RUNS_SHA256}", "not valid JSON")
        if not (isinstance(shas, list) and shas and all(_is_sha256(x) for x in shas)):
            fail(f"attrs {RUNS_SHA256}", "expected a JSON list of SHA-256 hex digests")


def _is_sha256(text) -> bool:
    return isinstance(text, str) and len(text) == 64 and all(c in "0123456789abcdef" for c in text)


def runs_sha256(plan: Plan) -> list:
    """The SHA-256 of the run files ``plan`` was made from, in order ([] when the plan does
    not say: a plan of another program or of tacest before 0.2)."""
    raw = plan.extra_attrs.get(RUNS_SHA256)
    return [] if raw is None else list(json.loads(attr_str(raw)))


def check_plan_continues(plan: Plan, run_path) -> None:
    """TacestError unless the run file ``run_path`` is the run ``plan`` was planned to
    continue: the last of its ``runs_sha256`` (the object in the state the poke was
    planned for).  A plan without ``runs_sha256`` cannot be checked and is accepted."""
    from tacest.errors import TacestError
    from tacest.io.h5util import sha256_file

    shas = runs_sha256(plan)
    if not shas:
        return
    sha = sha256_file(run_path)
    if sha != shas[-1]:
        what = ("an earlier run of its object; the poke continues the last one" if sha in shas else
                "another run (another object, or the run changed since)")
        raise TacestError(f"{plan.filename or 'plan'}: was planned from run SHA-256 {shas[-1][:12]}... "
                          f"(attrs {RUNS_SHA256}), but {run_path} has {sha[:12]}...: {what}")


def write_plan(plan: Plan, path) -> None:
    """Validate ``plan`` and write it atomically to ``path``."""
    _validate(plan, path)
    names = np.array([str(n) for n in plan.names], dtype=object)
    with atomic_h5(path) as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        f.attrs["method"] = str(plan.method)
        f.attrs["score"] = str(plan.score)
        f.attrs["estimate_sha256"] = str(plan.estimate_sha256)
        for k, v in plan.extra_attrs.items():
            f.attrs[k] = v
        f.attrs.update(provenance())
        cg = f.create_group("candidates")
        d = cg.create_dataset("params", data=np.asarray(plan.candidates, float).reshape(-1, plan.n_params))
        d.attrs["kind"] = str(plan.kind)
        d.attrs["names"] = names
        cg.create_dataset("score", data=np.asarray(plan.scores, float).reshape(-1))
        d = f.create_group("chosen").create_dataset("params", data=np.asarray(plan.chosen, float))
        d.attrs["kind"] = str(plan.kind)
        d.attrs["names"] = names


def read_plan(path) -> Plan:
    """Read and validate a plan file; a bad file raises FileFormatError naming file and path."""
    with open_h5(path) as f:
        r = Reader(f, path)
        if "format" in f.attrs:
            fmt = attr_str(f.attrs["format"])
            if fmt != FORMAT:
                r.fail("attrs format", f"expected {FORMAT!r}, got {fmt!r}")
        if "version" in f.attrs:
            version = r.attr_int("/", "version")
            if version != VERSION:
                r.fail("attrs version", f"unknown version {version} (this tacest reads version {VERSION})")
        chosen = r.dataset("/chosen/params", (None,))
        n = chosen.shape[0]
        candidates = r.dataset("/candidates/params", (None, n))
        scores = r.dataset("/candidates/score", (candidates.shape[0],), allow_nan=True)
        holder = "/chosen/params"
        attrs = f[holder].attrs
        if "names" in attrs:
            names = [attr_str(x) for x in np.atleast_1d(attrs["names"])]
        elif n == len(POKE_NAMES):
            names = list(POKE_NAMES)
        else:
            r.fail("/chosen/params attrs names", f"required attribute is missing (n = {n} is not a poke)")
        kind = attr_str(attrs.get("kind", "poke"))
        method = attr_str(r.attr("/", "method"))
        score = attr_str(r.attr("/", "score"))
        sha = attr_str(f.attrs.get("estimate_sha256", ""))
        extra = {k: f.attrs[k] for k in f.attrs
                 if k not in ("format", "version", "method", "score", "estimate_sha256", *PROVENANCE_ATTRS)}
    plan = Plan(chosen=chosen, candidates=candidates, scores=scores, method=method, score=score,
                estimate_sha256=sha, names=names, kind=kind, extra_attrs=extra, filename=str(path))
    _validate(plan, path)
    return plan
