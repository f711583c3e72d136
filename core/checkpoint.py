"""Checkpoints of long runs: resume an interrupted run, reuse a result only when its
recorded inputs match (issue #16; design.md "one output policy for every verb").

Two pieces, shared by ``glossrig extract``, ``glossrig diagnose`` and ``glossrig demo``:

* an input **fingerprint** (:func:`fingerprint`): the sha256 of every input file, the
  run's options, the glossrig version and the source commit. A capture folder is fingerprinted by its
  manifest (:func:`capture_sha256`): capture.json records every raw file's checksum
  and every raw read verifies it, so the manifest stands for the whole capture.
  A step's result is reused only when its recorded fingerprint equals the current one
  (:func:`read_record`, :func:`write_record`, :func:`record_matches`).
* a **work folder** of finished units (:class:`WorkStore`): a long run stores each unit
  it finishes (one LED of one rotation of an extraction, one stage of a diagnosis)
  under the run's fingerprint; ``resume=True`` reuses the units of an interrupted run
  with the same fingerprint and computes only the rest, so the resumed result equals
  an uninterrupted one. Tables are stored as Parquet (exact round trip of the
  columns and dtypes), other results with :mod:`pickle`; every file is written to a
  temporary name and renamed, so an interruption mid-write leaves no half unit.
  The verb removes the work folder once its output is written.
"""
from __future__ import annotations

import json
import logging
import os
import pickle
import re
import shutil
from pathlib import Path
from collections.abc import Callable
from typing import Any

from glossrig.core.atomic import atomic_write, atomic_write_json
from glossrig.core.capture import MANIFEST, sha256_file
from glossrig.core.errors import InputError
from glossrig.core.toml_input import read_json

_log = logging.getLogger(__name__)

#: name of the fingerprint file of a work folder
INPUTS = "inputs.json"


def glossrig_version() -> str:
    """The glossrig version (recorded with every fingerprint: a new version redoes);
    :func:`glossrig.core.resources.package_version`."""
    from glossrig.core.resources import package_version

    return package_version()


def source_commit() -> str | None:
    """The git commit of the running code when it is a checkout (None when installed):
    recorded with every fingerprint, so a result made by other code is not reused. Edits
    not yet committed are not seen; commit before relying on reuse across code changes."""
    from glossrig.core.provenance import source_revision

    rev = source_revision()
    return None if rev is None else rev["commit"]


def capture_sha256(folder) -> str:
    """sha256 of a capture folder's manifest (it records every raw file's checksum)."""
    p = Path(folder) / MANIFEST
    if not p.is_file():
        raise InputError("no capture.json: not a capture folder", path=Path(folder))
    return sha256_file(p)


def _jsonable(x: Any) -> Any:
    """Options as plain JSON values (paths as strings, tuples as lists, numpy scalars as numbers)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in sorted(x.items(), key=lambda kv: str(kv[0]))}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    if hasattr(x, "tolist"):                     # numpy arrays and scalars
        return _jsonable(x.tolist())
    return x


def fingerprint(files: dict | None = None, options: dict | None = None, captures: dict | None = None) -> dict:
    """What a result depends on: ``files`` (name -> path, hashed; None stays None),
    ``captures`` (name -> capture folder, hashed by manifest), ``options`` (JSON values)
    and the glossrig version and source commit. Two fingerprints are equal iff all of these are."""
    fp = {"files": {k: (sha256_file(v) if v is not None else None) for k, v in sorted((files or {}).items())},
          "captures": {k: capture_sha256(v) for k, v in sorted((captures or {}).items())},
          "options": _jsonable(options or {}), "version": glossrig_version(), "source": source_commit()}
    # through JSON once, so a fingerprint compares equal to the same one read back from a file
    return json.loads(json.dumps(fp))


def write_record(path, doc: dict) -> None:
    """Write a JSON record atomically (a reader never sees half of it)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(p, doc, sort_keys=True)


def read_record(path) -> dict | None:
    """A record written by :func:`write_record`, or None when missing or unreadable."""
    try:
        d = read_json(path, "record")
    except InputError:
        return None
    return d if isinstance(d, dict) else None


def record_matches(path, fp: dict) -> bool:
    """True when the record at ``path`` holds exactly the fingerprint ``fp`` (key ``inputs``)."""
    rec = read_record(path)
    return rec is not None and rec.get("inputs") == fp


def work_folder_for(output) -> Path:
    """The work folder of a run writing ``output``: ``OUTPUT.partial`` beside it."""
    p = Path(output)
    return p.with_name(p.name + ".partial")


def _unit_stem(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9_.=+-]+", name) or name.startswith("."):
        raise ValueError(f"checkpoint unit names are plain file names, got {name!r}")
    return name


class WorkStore:
    """A work folder of the finished units of one run, valid for one input fingerprint.

    ``resume=False`` starts afresh: an earlier work folder is discarded. ``resume=True``
    keeps the units of an earlier run whose fingerprint equals ``fp`` (a different
    fingerprint discards them, with a log line saying so). A folder that is not a
    glossrig work folder (non-empty, no inputs.json) is refused, never removed.
    """

    def __init__(self, folder, fp: dict, resume: bool = False, log: Callable[[str], None] | None = None):
        self.folder = Path(folder)
        self.fp = fp
        log = log or _log.info
        self.reused: list[str] = []
        if self.folder.exists():
            if not self.folder.is_dir() or (any(self.folder.iterdir()) and not (self.folder / INPUTS).is_file()):
                raise InputError("is in the way of the run's work folder and is not one; remove it or choose "
                                 "another output", path=self.folder)
            same = record_matches(self.folder / INPUTS, fp)
            if resume and same:
                self.reused = sorted(self.units())
                log(f"resume: reusing {len(self.reused)} finished unit(s) from {self.folder}")
            else:
                if any(self.folder.iterdir()):
                    why = ("its recorded inputs differ from this run's" if resume
                           else "not resuming (use --resume to continue it)")
                    log(f"discarding the interrupted run's work in {self.folder}: {why}")
                shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        write_record(self.folder / INPUTS, {"inputs": fp})

    def units(self) -> list[str]:
        """Names of the stored units."""
        return [p.stem for p in self.folder.iterdir()
                if p.is_file() and p.suffix in (".parquet", ".pkl") and not p.name.startswith(".")]

    def has(self, name: str) -> bool:
        s = _unit_stem(name)
        return (self.folder / f"{s}.parquet").is_file() or (self.folder / f"{s}.pkl").is_file()

    def load(self, name: str):
        """A stored unit (a DataFrame for a table, else the pickled object)."""
        s = _unit_stem(name)
        p = self.folder / f"{s}.parquet"
        if p.is_file():
            import pandas as pd

            return pd.read_parquet(p)
        with open(self.folder / f"{s}.pkl", "rb") as f:
            return pickle.load(f)

    def save(self, name: str, value) -> None:
        """Store a finished unit (atomically)."""
        import pandas as pd

        s = _unit_stem(name)
        if isinstance(value, pd.DataFrame):
            atomic_write(self.folder / f"{s}.parquet", lambda t: value.to_parquet(t, index=True))
        else:
            def dump(t: Path) -> None:
                with open(t, "wb") as f:
                    pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
            atomic_write(self.folder / f"{s}.pkl", dump)

    def get_or_compute(self, name: str, compute: Callable[[], Any]):
        """The stored unit ``name``, or ``compute()`` stored as it."""
        if self.has(name):
            return self.load(name)
        value = compute()
        self.save(name, value)
        return value

    def remove(self) -> None:
        """Remove the work folder (its output is written)."""
        shutil.rmtree(self.folder, ignore_errors=True)
