"""Per-sample CasADi functions compiled to C and cached on disk (optional speed-up).

The 3-D estimator maps a few small SX functions (residuals, their Jacobian, the
kinematics and their second derivatives) over thousands of samples.  CasADi's virtual
machine interprets them at ~10 ns per instruction; compiled C is ~8x faster.  The
functions depend only on the shape parameterization and the number of fingers, not on
the data or run lengths, so each is compiled once per machine and reused.

:func:`compile_functions` generates C for a set of functions (with the forward and
reverse derivatives CasADi's automatic differentiation asks for), compiles it with the
system C compiler (``$CC``, else ``cc`` or ``gcc``) into
``$TACEST_CACHE`` (default ``$XDG_CACHE_HOME/tacest`` or ``~/.cache/tacest``)``/kernels/``
under a name that hashes the generated source, and loads it with ``casadi.external``.
Without a compiler, when ``TACEST_NO_COMPILE=1`` or when compiling fails, the functions are
returned as they are (same results, slower).

Several processes may ask for the same kernel at once (the workers of a Dask cluster on
one machine, docs/parallel.md): one compiles it, under an exclusive lock on
``NAME.so.lock`` beside it, into a temporary file of its own that it renames into place
(atomic); the others wait for the lock, find the kernel there and load it.  A kernel
file that exists is therefore always complete, and each is compiled once per machine
(per cache folder).
"""

from __future__ import annotations

import logging

import contextlib
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca

log = logging.getLogger(__name__)

#: compiler flags: -O1 compiles a 15k-instruction function in ~5 s and runs within
#: 20 % of -O2, which takes nearly twice as long to compile
CFLAGS = ("-O1", "-fPIC", "-shared")
#: s, longest a compilation may take before we fall back to the virtual machine
COMPILE_TIMEOUT = 600


def cache_dir() -> Path:
    base = os.environ.get("TACEST_CACHE")
    if base:
        return Path(base) / "kernels"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return Path(xdg or Path.home() / ".cache") / "tacest" / "kernels"


def _compiler():
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@contextlib.contextmanager
def _exclusive(lock_path: Path):
    """Hold an exclusive lock on ``lock_path`` (created if missing) for the block: one
    process (or thread) at a time.  Without fcntl (not POSIX) the block runs unlocked:
    the atomic rename alone keeps kernel files complete, at the price of compiling twice."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(lock_path, "a+b") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _build(src: Path, target: Path, tag: str) -> bool:
    """Compile ``src`` into ``target`` unless another process did meanwhile (under the
    lock of the module doc); False when compiling is not possible."""
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with _exclusive(target.with_name(target.name + ".lock")):
            if target.exists():  # compiled by another process while this one waited
                return True
            log.info(f"compiling {tag} kernels (once per machine) ...")
            fd, part = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
            os.close(fd)
            try:
                subprocess.run([_compiler(), *CFLAGS, "-o", part, str(src), "-lm"], check=True,
                               capture_output=True, timeout=COMPILE_TIMEOUT)
                os.chmod(part, 0o755)
                os.replace(part, target)
            finally:
                if os.path.exists(part):
                    os.unlink(part)
    except (OSError, subprocess.SubprocessError):
        return False
    return True


def compile_functions(funs, tag: str, derivatives=()):
    """{name: Function}: the functions ``funs`` (SX), compiled and loaded, or as given
    when compiling is not possible.

    derivatives : names of functions (among funs) whose first forward and reverse
    derivatives are compiled too, so that CasADi's AD through them stays compiled.
    """
    plain = {f.name(): f for f in funs}
    if os.environ.get("TACEST_NO_COMPILE") or _compiler() is None:
        return plain
    with tempfile.TemporaryDirectory(prefix="tacest_cg_") as tmp:
        cg = ca.CodeGenerator(f"{tag}.c", {"with_header": False})
        for f in funs:
            cg.add(f)
            if f.name() in derivatives:
                cg.add(f.forward(1))
                cg.add(f.reverse(1))
        cg.generate(tmp + os.sep)
        src = Path(tmp) / f"{tag}.c"
        code = src.read_bytes()
        key = hashlib.sha256(code + ca.__version__.encode() + " ".join(CFLAGS).encode()).hexdigest()[:16]
        target = cache_dir() / f"{tag}_{key}.so"
        if not target.exists() and not _build(src, target, tag):
            return plain
    try:
        return {name: ca.external(name, str(target)) for name in plain}
    except RuntimeError:
        return plain
