"""The steps of a multi-step verb (``glossrig measure``, ``glossrig demo``): each step's
result is reused only when its recorded inputs match (issue #16, design.md "one output
policy for every verb"; the fingerprint is :func:`glossrig.core.checkpoint.fingerprint`).

A step writes some outputs (files, folders, capture folders) in the verb's working
folder ``OUT`` from some inputs. :meth:`StepRunner.run` records in
``OUT/.steps/NAME.json`` what the step was run with - the sha256 of its input files, of
its input captures (by their manifests, which record every raw file's checksum), its
options and the glossrig version - and, once it finished, the digest of what it wrote.
With ``resume`` a step is skipped only when all of that matches (an output edited since
is redone); so a changed input redoes exactly the steps downstream of it, because each
downstream step has the upstream output among its inputs. A step interrupted with the
same inputs is continued (``compute(resume=True)``) when it can resume its own work
(``resumable``); otherwise, or when continuing fails, or when a finished step's output
was changed since, what it left is removed and it is redone. Without ``resume`` every step is redone (the verb refused an existing
output before, unless ``--force``).
"""
from __future__ import annotations

import hashlib
import logging
import shutil
import time
from pathlib import Path
from collections.abc import Callable, Iterable

from glossrig.core.checkpoint import capture_sha256, fingerprint, read_record, work_folder_for, write_record
from glossrig.core.errors import GlossrigError

_log = logging.getLogger(__name__)

#: folder of the step records inside a verb's working folder
STEPS = ".steps"


def output_digest(p: Path) -> str | None:
    """What a step left at ``p``: a capture folder by its manifest's sha256, another folder by
    the sha256 of its files' relative paths and sha256s (hidden files excepted), a file by its
    sha256; None when missing."""
    from glossrig.core.capture import sha256_file

    p = Path(p)
    if p.is_dir():
        if (p / "capture.json").is_file():
            return capture_sha256(p)
        h = hashlib.sha256()
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            rel = f.relative_to(p)
            if any(part.startswith(".") for part in rel.parts):
                continue
            h.update(f"{rel.as_posix()}\0{sha256_file(f)}\n".encode())
        return h.hexdigest()
    return sha256_file(p) if p.is_file() else None


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()


class StepRunner:
    """Runs the steps of one verb in its working folder ``out`` (module docstring).

    ``resume``: reuse finished steps whose recorded inputs match, continue an interrupted
    one. ``total``: the number of steps, for the progress lines (``step K/N NAME``).
    ``done`` and ``reused`` list the steps run and reused in this run, in order."""

    def __init__(self, out, *, resume: bool, total: int | None = None, log: logging.Logger | None = None):
        self.out = Path(out)
        self.resume = resume
        self.total = total
        self.log = log or _log
        self.k = 0
        self.done: list[str] = []
        self.reused: list[str] = []

    def record_path(self, name: str) -> Path:
        return self.out / STEPS / f"{name}.json"

    def _key(self, p: Path) -> str:
        try:
            return Path(p).relative_to(self.out).as_posix()
        except ValueError:
            return str(p)

    def digests(self, outputs: Iterable[Path]) -> dict:
        return {self._key(p): output_digest(p) for p in outputs}

    def run(self, name: str, outputs, compute: Callable[[bool], None], *, files: dict | None = None,
            captures: dict | None = None, options: dict | None = None, resumable: bool = False) -> bool:
        """Run step ``name`` unless a finished run with the same inputs wrote ``outputs``
        (a path or a list of paths) as they are now. ``compute(resume)`` does the work,
        raising on failure (a :class:`~glossrig.core.errors.GlossrigError` for bad input);
        ``resume=True`` asks it to continue its own interrupted work. ``files``,
        ``captures``, ``options``: the step's inputs (:func:`fingerprint`). Returns True
        when the step ran, False when it was reused."""
        outs = [Path(outputs)] if isinstance(outputs, (str, Path)) else [Path(p) for p in outputs]
        self.k += 1
        tag = f"step {self.k}/{self.total} {name}" if self.total else f"step {name}"
        record = self.record_path(name)
        fp = fingerprint(files=files, captures=captures, options=options)
        rec = read_record(record) or {}
        same = rec.get("inputs") == fp
        if self.resume and same and rec.get("finished") and self.digests(outs) == rec.get("output"):
            self.log.info(f"{tag}: reusing {', '.join(self._key(p) for p in outs)} (recorded inputs match)")
            self.reused.append(name)
            return False
        t0 = time.perf_counter()
        left = any(p.exists() or work_folder_for(p).exists() for p in outs)
        why = ("not resuming" if not self.resume else "no earlier run" if not rec else
               "its inputs changed" if not same else "its output changed since" if rec.get("finished")
               else "interrupted")
        write_record(record, {"inputs": fp, "finished": False})
        finished = False
        if self.resume and same and not rec.get("finished") and left and resumable:
            self.log.info(f"{tag}: continuing the interrupted run")
            try:
                compute(True)
                finished = True
            except GlossrigError as e:
                self.log.warning(f"could not continue the interrupted {name} step ({e}); redoing it")
        if not finished:
            if left:
                for p in outs:          # stale (other inputs) or half-written: the verb owns these outputs
                    _remove(p)
                    shutil.rmtree(work_folder_for(p), ignore_errors=True)
            self.log.info(f"{tag}: running ({why})")
            compute(False)
        write_record(record, {"inputs": fp, "finished": True, "output": self.digests(outs)})
        self.log.info(f"{tag}: done in {time.perf_counter() - t0:.1f} s")
        self.done.append(name)
        return True
