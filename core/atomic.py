"""The one atomic file write (design.md: "nothing already written is lost or overwritten";
a crash never leaves half a file).

Every file glossrig writes goes through :func:`atomic_write`: the content is written to a
temporary file in the target's folder (``.NAME.XXXXXXXX.part``: hidden, and recognisable
as unfinished by the verbs that clean up after an interrupted run), given mode 0644
(mkstemp's 0600 would hide shared lab data from other users), fsynced, then renamed into
place (or, with ``overwrite=False``, hard-linked, which never replaces a file that
appeared meanwhile) and the folder fsynced. A reader sees the old file or the new one,
never a mix; on any failure the temporary file is removed and the target is untouched.
"""
from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

#: mode of every file written (rw-r--r--)
MODE = 0o644

# errors of os.link on a filesystem or folder without (more) hard links: check, then rename
_NO_LINK = (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK)


def fsync_file(path: str | Path) -> None:
    """fsync a file written (and closed) by other code, so its content is on disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(folder: str | Path) -> None:
    """fsync a folder, so a rename or link in it survives a crash (best effort: some
    filesystems and platforms cannot open or fsync a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def publish(tmp: str | Path, path: str | Path, *, overwrite: bool = True) -> None:
    """Give the finished (and fsynced) temporary file ``tmp`` the name ``path``, in the same
    folder, atomically. With ``overwrite`` an existing ``path`` is replaced; without, a
    hard link is made, which fails when ``path`` exists (raising :class:`FileExistsError`,
    ``tmp`` kept), so a file that appeared meanwhile is never clobbered. The folder is
    fsynced afterwards."""
    path = Path(path)
    if overwrite:
        os.replace(tmp, path)
    else:
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise FileExistsError(errno.EEXIST, "refusing to replace an existing file", str(path)) from None
        except OSError as e:
            if e.errno not in _NO_LINK:
                raise
            if path.exists():
                raise FileExistsError(errno.EEXIST, "refusing to replace an existing file", str(path)) from None
            os.replace(tmp, path)
        else:
            os.unlink(tmp)
    fsync_dir(path.parent)


def _remove(tmp: str | Path) -> None:
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def atomic_write(path: str | Path, write: Callable[[Path], object], *, overwrite: bool = True) -> Path:
    """Write ``path`` atomically (module docstring): ``write(tmp)`` fills the temporary
    file ``tmp`` (a :class:`~pathlib.Path` that exists, empty, in ``path``'s folder; ``write``
    may open it or replace it by name). ``overwrite=False`` raises :class:`FileExistsError`
    when ``path`` exists by the time the file is complete. Returns ``path``."""
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    tmp = Path(name)
    try:
        os.close(fd)
        write(tmp)
        os.chmod(tmp, MODE)
        fsync_file(tmp)
        publish(tmp, path, overwrite=overwrite)
    except BaseException:
        _remove(tmp)
        raise
    return path


def atomic_write_bytes(path: str | Path, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data), overwrite=overwrite)


def atomic_write_text(path: str | Path, text: str, *, overwrite: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_write`)."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def atomic_write_json(path: str | Path, obj, *, indent: int = 1, overwrite: bool = True, **dumps) -> Path:
    """Write ``obj`` as JSON (``json.dumps(obj, indent=indent, **dumps)`` and a final
    newline) to ``path`` atomically (:func:`atomic_write`)."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, **dumps) + "\n", overwrite=overwrite)
