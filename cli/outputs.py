"""One policy for the files and folders a verb writes (issue #16).

Every writing verb calls :func:`prepare_output` for each of its outputs at the
start of ``run()``, after argument parsing and before any computation, so that a
run which cannot keep its result fails in well under a second, not after an hour
of work:

* an existing output is refused unless ``--force`` (:func:`add_force_option`)
  or, for a verb that resumes its own partial output, ``resume=True``;
* the folder the output goes into must exist (or, where the verb creates it, its
  nearest existing ancestor must be a folder) and must be writable: a probe file
  is created and removed there;
* every refusal is an :class:`~glossrig.core.errors.InputError` naming the path,
  which the CLI prints as one line with exit status 2.

Nothing is created or removed by the check itself (the probe file excepted), so a
refused run leaves the file system as it found it.
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from collections.abc import Iterable

from glossrig.core.errors import InputError

FORCE_HINT = "use --force to overwrite"


def add_force_option(parser: argparse.ArgumentParser, what: str = "existing output files") -> None:
    """Add the one ``--force`` option every writing verb has (``args.force``)."""
    parser.add_argument("--force", action="store_true", help=f"replace {what} (otherwise an existing output is "
                                                             "refused before any work is done)")


def _nearest_existing(p: Path) -> Path:
    q = p
    while not q.exists() and q != q.parent:
        q = q.parent
    return q


def _probe(folder: Path, shown: Path) -> None:
    """Create and remove a file in ``folder``; an OSError becomes an InputError naming ``shown``."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".glossrig-write-test-", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise InputError(f"cannot write here: {e.strerror or e}", path=shown) from None


def _check_folder_for(target: Path, make_parents: bool) -> None:
    """The folder ``target`` is written into exists (or can be created) and is writable."""
    parent = target.parent if str(target.parent) else Path(".")
    if parent.is_dir():
        _probe(parent, target)
        return
    anc = _nearest_existing(parent)
    if anc.exists() and not anc.is_dir():
        raise InputError(f"cannot write here: {anc} is a file, not a folder", path=target)
    if not make_parents:
        raise InputError("output folder does not exist", path=target)
    _probe(anc if str(anc) else Path("."), target)


def prepare_output(path, force: bool = False, *, kind: str = "file", resume: bool = False,
                   make_parents: bool = False, names: Iterable[str] | None = None,
                   hint: str = FORCE_HINT) -> Path:
    """Check that ``path`` may be written; return it as a :class:`~pathlib.Path`.

    ``kind="file"``: an existing file is refused unless ``force`` or ``resume``; a
    folder in its place is always refused. Its folder must exist unless
    ``make_parents`` (the verb creates it), and be writable.

    ``kind="folder"``: a folder the verb fills. An existing non-empty folder is
    refused unless ``force`` or ``resume``; with ``names``, only those entries count
    (a verb that writes a fixed set of files into a shared folder). A file in its
    place is always refused. A missing folder is not created here; its nearest
    existing ancestor must be a writable folder.

    ``resume=True`` says an existing output is the verb's own partial result, which
    it will complete: it is accepted as with ``force``. ``hint`` ends the refusal
    message (default: "use --force to overwrite").
    """
    p = Path(path)
    if kind == "file":
        if p.is_dir():
            raise InputError("is a folder; expected a file to write", path=p)
        if (p.exists() or p.is_symlink()) and not (force or resume):
            raise InputError(f"exists; {hint}", path=p)
        _check_folder_for(p, make_parents)
        return p
    if kind != "folder":
        raise ValueError(f"kind must be 'file' or 'folder', got {kind!r}")
    if p.exists() and not p.is_dir():
        raise InputError("exists and is not a folder", path=p)
    if p.is_dir():
        try:
            entries = [e.name for e in p.iterdir()]
        except OSError as e:
            raise InputError(f"cannot read the folder: {e.strerror or e}", path=p) from None
        clash = sorted(set(entries) & set(names)) if names is not None else entries
        if clash and not (force or resume):
            what = f"already holds {', '.join(clash)}" if names is not None else "exists and is not empty"
            raise InputError(f"{what}; {hint}", path=p)
        _probe(p, p)
        return p
    anc = _nearest_existing(p)
    if anc.exists() and not anc.is_dir():
        raise InputError(f"cannot write here: {anc} is a file, not a folder", path=p)
    _probe(anc if str(anc) else Path("."), p)
    return p
