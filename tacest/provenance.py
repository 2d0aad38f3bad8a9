"""Provenance: which tacest, and which command line, wrote a file.

Every run, estimate and plan file gets the root attrs ``tacest_version`` and
``command_line`` (docs/formats.md, "Provenance"), and every diagnosis report the same
keys in diagnosis.json.  The command line is the one the ``tacest`` entry point was
given (:func:`set_command_line`, called by cli/main.py); a program that calls the library
directly is recorded by its own ``sys.argv``.
"""

from __future__ import annotations

import hashlib
import shlex
import sys

from tacest import __version__

#: root attrs that say who wrote a file; a reader does not carry them over (a file
#: written from what it read gets its own)
PROVENANCE_ATTRS = ("tacest_version", "command_line", "command_line_sha256")

_command_line: str | None = None


def set_command_line(argv) -> None:
    """Record the arguments of this ``tacest`` invocation (without the program name);
    None forgets them (the entry point does, when the command ends)."""
    global _command_line
    _command_line = None if argv is None else shlex.join(["tacest", *map(str, argv)])


def command_line() -> str:
    """The command line of this process, shell-quoted: ``tacest ...`` when run through the
    entry point, else the Python program's own arguments."""
    if _command_line is not None:
        return _command_line
    return shlex.join(map(str, sys.argv)) if sys.argv and sys.argv[0] else "python"


def provenance() -> dict:
    """``{"tacest_version": ..., "command_line": ...}`` for a file being written."""
    return {"tacest_version": __version__, "command_line": command_line()}


def sha256_text(text: str) -> str:
    """Hex SHA-256 of a text (UTF-8): a commitment to a value a blind file must not show."""
    return hashlib.sha256(str(text).encode("utf-8")).hexdigest()


#: what :func:`source_digest` hashes of the package: its code and its shipped settings
SOURCE_SUFFIXES = (".py", ".toml")


def source_digest(*extra_files) -> str:
    """The code version a result belongs to: the first 12 hex digits of the SHA-256 of
    every tacest source file (``SOURCE_SUFFIXES`` under the installed package, each by
    its path relative to the package and its bytes, in sorted order) and of
    ``extra_files`` (paths, e.g. the benchmark script that made the result, by name and
    bytes).  Any edit to any of them changes it; a benchmark keys its cache by it, so
    that a table never mixes results of two versions."""
    from pathlib import Path

    import tacest

    root = Path(tacest.__file__).resolve().parent
    h = hashlib.sha256()
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in SOURCE_SUFFIXES
                   and "__pycache__" not in p.parts)
    for p in files:
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    for f in extra_files:
        p = Path(f)
        h.update(b"extra:" + p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:12]
