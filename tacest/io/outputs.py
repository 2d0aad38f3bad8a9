"""Where a command may write: the one check of every output path, and the writers of
output folders.

:func:`check_output` is called by every command on its outputs before any work (so a
bad ``-o`` fails in a second, not after minutes of solving) and by the file writers
(:func:`tacest.io.h5util.atomic_h5`, :func:`atomic_dir`, :func:`replacing_files`) as a
last guard.  It refuses:

- an output that is one of the command's inputs (the same file: same device and inode,
  so a hard link or another spelling of the path is caught too), or, for an output
  folder, a folder that holds an input;
- an existing output that is not a regular file (a folder, FIFO, device, socket) — or,
  for an output folder, not a folder: tacest replaces only what it writes;
- an output path that is a symbolic link: a write renames a new file into place, which
  would replace the link itself, and writing through it would replace a file elsewhere
  under another name; tacest does neither (docs/formats.md, "Outputs");
- an output whose folder does not exist or cannot be written (checked by creating and
  removing a probe file there, which also catches read-only file systems and root's
  writes to them).

Every refusal is a :class:`TacestError` naming the path, one line.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from pathlib import Path

from tacest.errors import TacestError
from tacest.interrupt import raise_if_noted


def _folder_of(path: Path) -> Path:
    return path.parent if str(path.parent) else Path(".")


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _inside(path, folder: Path) -> bool:
    try:
        return Path(path).resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):
        return False


def check_writable_folder(folder, what) -> None:
    """TacestError unless ``folder`` exists and a file can be created in it (a probe
    file is created and removed); ``what`` is the output named in the message."""
    folder = Path(folder)
    if not folder.is_dir():
        raise TacestError(f"{what}: folder {folder} does not exist")
    try:
        fd, probe = tempfile.mkstemp(prefix=".tacest-probe.", dir=folder)
    except OSError as exc:
        raise TacestError(f"{what}: cannot write in folder {folder} ({exc.strerror or exc.__class__.__name__})") \
            from None
    os.close(fd)
    os.unlink(probe)


def check_output(path, inputs=(), folder: bool = False, probe: bool = True) -> Path:
    """Check that a command may write its output ``path`` (module doc); returns it as a Path.

    inputs : the command's input paths (None entries are skipped);
    folder : ``path`` is an output folder (its contents are written or replaced);
    probe : also check that the folder is writable by creating a probe file there.
    """
    path = Path(path)
    if path.is_symlink():
        raise TacestError(f"{path}: is a symbolic link; tacest does not write through links "
                          "(give the path of its target, or remove the link)")
    if path.exists():
        mode = path.stat().st_mode
        if folder and not stat.S_ISDIR(mode):
            raise TacestError(f"{path}: exists and is not a folder")
        if not folder and stat.S_ISDIR(mode):
            raise TacestError(f"{path}: is a folder; give a file name")
        if not folder and not stat.S_ISREG(mode):
            raise TacestError(f"{path}: exists and is not a regular file (a FIFO, device or socket); "
                              "tacest replaces regular files only")
    for source in inputs:
        if source is None:
            continue
        if folder:
            if path.exists() and _inside(source, path):
                raise TacestError(f"{path}: the output folder holds the input {source}; "
                                  "write the output to another folder")
        elif _same_file(source, path):
            raise TacestError(f"{path}: is also an input ({source}); write the output to a new file")
    if probe:
        check_writable_folder(_folder_of(path), path)
    elif not _folder_of(path).is_dir():
        raise TacestError(f"{path}: folder {_folder_of(path)} does not exist")
    return path


def _finish_mode(path: Path, mode: int) -> None:
    """Give a finished temporary file or folder the permissions the umask asks for
    (mkstemp and mkdtemp make them private)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, mode & ~umask)


@contextlib.contextmanager
def atomic_file(path):
    """Yield a temporary path in the target's folder (``.NAME.*.part.EXT``, with the
    target's extension, so writers that choose the format by it work); rename it to
    ``path`` only when the ``with`` block finishes without error or interrupt (it is
    removed otherwise).

    So an existing ``path`` is untouched until the new file is complete, and a file that
    exists is always complete.
    """
    path = check_output(path, probe=False)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".part{path.suffix}", dir=_folder_of(path))
    except OSError as exc:
        raise TacestError(f"{path}: cannot write in folder {_folder_of(path)} "
                          f"({exc.strerror or exc.__class__.__name__})") from None
    os.close(fd)
    try:
        yield Path(tmp)
        raise_if_noted()  # a Ctrl-C that something caught meanwhile (tacest.interrupt)
        _finish_mode(Path(tmp), 0o666)
        check_output(path, probe=False)  # nothing replaced it with a link or a folder meanwhile
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_dir(path, marker: str = "report.md"):
    """Yield a temporary folder beside ``path``; on success it replaces ``path`` whole.

    An existing non-empty ``path`` is replaced only if it holds ``marker`` (an earlier
    output of the same command); on an error or an interrupt the temporary folder is
    removed and ``path`` is untouched.
    """
    path = check_output(path, folder=True)
    parent = _folder_of(path)
    if path.is_dir() and any(path.iterdir()) and not (path / marker).is_file():
        # never replace a folder that is not an earlier output of this kind
        raise TacestError(f"{path}: folder exists and is not an earlier output of this command (no {marker}); "
                          "choose a new or empty folder")
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=parent))
    try:
        yield tmp
        raise_if_noted()
        _finish_mode(tmp, 0o777)
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=parent))
            os.rmdir(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def replacing_files(path, names=()):
    """For a command that fills an output folder with files of known names (``tacest
    explore``, ``tacest demo``): yields the folder (created if missing), in which the
    command writes its files at their final names.

    ``names`` are glob patterns of the command's files.  An earlier run's files are
    first moved aside (to a temporary sibling folder); when the block ends normally or
    with an error they are deleted (an earlier run's file is never mistaken for this
    one's); on an interrupt (KeyboardInterrupt) the files written so far are removed and
    the earlier ones put back, so Ctrl-C leaves the folder as it was.  Other files in the
    folder are never touched.
    """
    path = check_output(path, folder=True)
    created = not path.exists()
    path.mkdir(exist_ok=True)
    aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=_folder_of(path)))

    def ours():
        return sorted({p for pattern in names for p in path.glob(pattern) if p.is_file() or p.is_symlink()})

    try:
        for old in ours():
            os.replace(old, aside / old.name)
        yield path
        raise_if_noted()
    except KeyboardInterrupt:
        for new in ours():
            new.unlink()
        for old in aside.iterdir():
            os.replace(old, path / old.name)
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()  # only if nothing else was put there meanwhile
        raise
    finally:
        shutil.rmtree(aside, ignore_errors=True)
