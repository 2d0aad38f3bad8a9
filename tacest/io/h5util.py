"""Small HDF5 helpers shared by every file type: atomic writes, safe opening,
and typed attribute/dataset access that fails with a :class:`FileFormatError`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from pathlib import Path

import numpy as np

from tacest.errors import FileFormatError, TacestError


@contextlib.contextmanager
def atomic_h5(path):
    """Open a new HDF5 file for writing under a temporary name in the target folder;
    rename it into place only when the ``with`` block finishes without error
    (:func:`tacest.io.outputs.atomic_file`, which also refuses a ``path`` that is a
    link, a folder or another non-regular file).

    A crash, an exception or an interrupt inside the block leaves ``path`` as it was
    (and removes the temporary file), so a file that exists always is complete.
    """
    import h5py

    from tacest.io.outputs import atomic_file

    with atomic_file(path) as tmp:
        with h5py.File(tmp, "w") as f:
            yield f


def open_h5(path):
    """Open an existing HDF5 file read-only; a missing or non-HDF5 file is a TacestError."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise TacestError(f"{path}: no such file")
    if path.is_dir():
        raise TacestError(f"{path}: is a folder, not an HDF5 file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise TacestError(f"{path}: not a readable HDF5 file ({exc.__class__.__name__})") from None


def sha256_file(path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def attr_str(value) -> str:
    """An HDF5 attribute as a Python str (h5py may hand back bytes or numpy str)."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.shape == ():
        return attr_str(value[()])
    return str(value)


class Reader:
    """Typed access to one open HDF5 file; every failure names file and path.

    Parameters
    ----------
    f : h5py.File
    filename : str, used in messages
    """

    def __init__(self, f, filename):
        self.f = f
        self.filename = str(filename)

    def fail(self, h5path, problem):
        raise FileFormatError(self.filename, h5path, problem)

    def has(self, h5path) -> bool:
        return h5path in self.f

    def attr(self, h5path, name, default=KeyError):
        obj = self.f[h5path] if h5path != "/" else self.f
        if name not in obj.attrs:
            if default is KeyError:
                self.fail(f"{h5path} attrs {name}" if h5path != "/" else f"attrs {name}",
                          "required attribute is missing")
            return default
        return obj.attrs[name]

    def attr_float(self, h5path, name, default=KeyError, positive=False) -> float:
        where = f"{h5path} attrs {name}" if h5path != "/" else f"attrs {name}"
        raw = self.attr(h5path, name, default)
        if raw is default and default is not KeyError:
            return default
        try:
            val = float(np.asarray(raw, dtype=float).reshape(()))
        except (TypeError, ValueError):
            self.fail(where, f"expected a number, got {raw!r}")
        if not np.isfinite(val):
            self.fail(where, f"must be finite, got {val}")
        if positive and not val > 0:
            self.fail(where, f"must be > 0, got {val}")
        return val

    def attr_int(self, h5path, name, default=KeyError) -> int:
        """An integer attribute (a float with an integral value is accepted)."""
        where = f"{h5path} attrs {name}" if h5path != "/" else f"attrs {name}"
        raw = self.attr(h5path, name, default)
        if raw is default and default is not KeyError:
            return default
        try:
            val = np.asarray(raw).reshape(())
            if val.dtype.kind not in "biuf" or not np.isfinite(val) or val != np.round(val):
                raise ValueError
            return int(val)
        except (TypeError, ValueError, OverflowError):
            self.fail(where, f"expected an integer, got {raw!r}")

    def attr_vector(self, h5path, name, length, default=KeyError) -> np.ndarray:
        where = f"{h5path} attrs {name}" if h5path != "/" else f"attrs {name}"
        raw = self.attr(h5path, name, default)
        if raw is default and default is not KeyError:
            return default
        try:
            arr = np.asarray(raw, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            self.fail(where, f"expected {length} numbers, got {raw!r}")
        if arr.shape != (length,):
            self.fail(where, f"expected shape ({length},), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            self.fail(where, "must be finite")
        return arr

    def dataset(self, h5path, shape, dtype=float, allow_nan=False) -> np.ndarray:
        """Read a dataset and check its shape; ``shape`` entries of None match anything.

        Returns the array with the requested dtype.  Non-finite values are an error
        unless ``allow_nan`` (then NaN is allowed, inf never is).
        """
        import h5py

        if h5path not in self.f:
            self.fail(h5path, "required dataset is missing")
        obj = self.f[h5path]
        if not isinstance(obj, h5py.Dataset):
            self.fail(h5path, "expected a dataset, found a group")
        if obj.dtype.kind not in "biuf":  # strings, complex, compound: not real numbers
            self.fail(h5path, f"expected real numbers, got {obj.dtype}")
        try:
            arr = np.asarray(obj[()], dtype=dtype)
        except (TypeError, ValueError, OverflowError):
            self.fail(h5path, f"cannot read as {np.dtype(dtype).name}")
        except OSError as exc:  # HDF5 could not read the data: a damaged file
            self.fail(h5path, f"cannot be read ({_first_line(exc)})")
        if len(arr.shape) != len(shape) or any(
            s is not None and s != a for s, a in zip(shape, arr.shape)
        ):
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            self.fail(h5path, f"expected shape {want}, got {arr.shape}")
        if np.issubdtype(arr.dtype, np.floating):
            if allow_nan:
                if np.any(np.isinf(arr)):
                    self.fail(h5path, "contains inf")
            elif not np.all(np.isfinite(arr)):
                self.fail(h5path, "contains NaN or inf where values are required")
        return arr


def _first_line(exc) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else exc.__class__.__name__


def json_attr(value) -> str:
    """Serialize a Python value as a JSON string attribute."""
    return json.dumps(value, sort_keys=True)
