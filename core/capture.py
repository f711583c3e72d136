"""The capture folder contract (design.md): ``DIR/capture.json`` + raw files.

Shared by the twin, the hardware layer and the pipeline. Top-level keys:
``rig`` (path of the rig description, relative to the capture folder or
absolute), ``rig_name``, ``material`` (a label only), ``complete`` (set once
every planned image is on disk) and ``images``: one entry per raw file with at
least ``file``, ``role`` (calibration / sequence / checkerboard), ``leds``,
``rotation`` (deg), ``repeat``, ``exposure_s``, ``iso``, ``aperture``, ``time``
(ISO 8601) and ``sha256``.

Writes are atomic (:mod:`glossrig.core.atomic`) so a crash never leaves a
half-written manifest; nothing already written is overwritten silently.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from glossrig.core.atomic import atomic_write_json
from glossrig.core.errors import InputError
from glossrig.core.toml_input import read_json

MANIFEST = "capture.json"
TRUTH = "truth.json"
ROLES = ("calibration", "sequence", "checkerboard")
REQUIRED = ("file", "role", "leds", "rotation", "repeat", "exposure_s", "iso", "aperture", "time", "sha256")
#: the copy of the rig description every capture folder holds, written when the capture starts
#: (``glossrig capture`` and ``glossrig simulate``); the manifest's ``rig`` names it
RIG_COPY = "rig.toml"


# ------------------------------------------------------------------ file names
#
# One naming scheme for every capture, whether the twin (``glossrig simulate``), the
# twin backends or the real rig (``glossrig capture``) takes it, so two captures of
# the same plan hold the same files. Readers never parse these names: the manifest
# lists every file with its role, LEDs, rotation, repeat and exposure, and captures
# written with older names (``seq_rp000_led05_rep0_e00.dng``) still read.

def rotation_tag(deg: float) -> str:
    """A sample rotation (degrees) as a file-name fragment, exact to 0.01 degree.

    A sign letter (``p`` for zero and positive, ``m`` for negative), at least three
    integer digits, a point and two decimals: 22 -> ``p022.00``, 22.5 -> ``p022.50``,
    -0.4 -> ``m000.40``, 0 and -0 -> ``p000.00``, 359.99 -> ``p359.99``. Rotations that
    differ by 0.01 degree or more never share a tag; :func:`check_rotation_tags`
    refuses a set of rotations closer than that (they would name the same files)."""
    x = float(deg)
    if x != x or x in (float("inf"), float("-inf")):
        raise InputError(f"rotation must be a finite number of degrees, got {deg!r}")
    hundredths = round(x * 100)        # integer arithmetic: no "-0.00", no float formatting surprises
    sign = "m" if hundredths < 0 else "p"
    whole, frac = divmod(abs(hundredths), 100)
    return f"{sign}{whole:03d}.{frac:02d}"


def check_rotation_tags(rotations, where=None) -> None:
    """Refuse rotations whose file names would collide (equal to 0.01 degree)."""
    seen: dict[str, float] = {}
    for r in rotations:
        t = rotation_tag(r)
        if t in seen and float(seen[t]) != float(r):
            raise InputError(f"rotations {seen[t]:g} and {float(r):g} degrees are closer than 0.01 degree: their "
                             f"images would have the same file names (rot{t}_...); give rotations to 0.01 degree",
                             path=where)
        seen.setdefault(t, r)


def image_stem(role: str, *, rotation: float = 0.0, leds=(), repeat: int = 0, exposure_index: int = 0,
               view: int | None = None) -> str:
    """The file name (without extension) of one planned image, unique within a plan.

    ``checkerboard_view03``; ``rotp045.00_calibration`` (all LEDs, one per rotation);
    ``rotm045.00_led06_rep1_exp07`` (LED ids as the rig numbers them, 1-16 on the thesis
    rig; several LEDs joined by ``-``; ``exp`` is the index in the LED's exposure
    sequence, shortest first)."""
    if role == "checkerboard":
        if view is None:
            raise InputError("a checkerboard image needs its view number")
        return f"checkerboard_view{int(view):02d}"
    rot = rotation_tag(rotation)
    if role == "calibration":
        return f"rot{rot}_calibration"
    if role == "sequence":
        led = "-".join(f"{int(i):02d}" for i in leds)
        return f"rot{rot}_led{led}_rep{int(repeat)}_exp{int(exposure_index):02d}"
    raise InputError(f"role {role!r} not one of {ROLES}")


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class ImageEntry:
    file: str
    role: str
    leds: list[int]
    rotation: float
    repeat: int
    exposure_s: float
    iso: int
    aperture: float
    time: str
    sha256: str
    extra: dict = field(default_factory=dict)

    def key(self) -> tuple:
        """What identifies a planned shot (used for resume)."""
        return (self.role, tuple(self.leds), float(self.rotation), int(self.repeat), float(self.exposure_s),
                self.extra.get("view"))

    def to_json(self) -> dict:
        d = asdict(self)
        extra = d.pop("extra")
        d.update(extra)
        return d

    @classmethod
    def from_json(cls, d: dict, where: str) -> ImageEntry:
        missing = [k for k in REQUIRED if k not in d]
        if missing:
            raise InputError(f"image entry {d.get('file', '?')!r} lacks {', '.join(missing)}", path=where)
        if d["role"] not in ROLES:
            raise InputError(f"image {d['file']!r}: role {d['role']!r} not one of {ROLES}", path=where)
        try:
            exp = float(d["exposure_s"])
        except (TypeError, ValueError):
            raise InputError(f"image {d['file']!r}: exposure_s {d['exposure_s']!r} is not a number", path=where) from None
        if not exp > 0:
            raise InputError(f"image {d['file']!r}: exposure_s must be > 0, got {exp}", path=where)
        extra = {k: v for k, v in d.items() if k not in REQUIRED}
        return cls(file=str(d["file"]), role=d["role"], leds=[int(x) for x in d["leds"]], rotation=float(d["rotation"]),
                   repeat=int(d["repeat"]), exposure_s=exp, iso=int(d["iso"]), aperture=float(d["aperture"]),
                   time=str(d["time"]), sha256=str(d["sha256"]), extra=extra)


@dataclass
class Manifest:
    folder: Path
    rig: str
    material: str
    images: list[ImageEntry] = field(default_factory=list)
    complete: bool = False
    meta: dict = field(default_factory=dict)

    @property
    def path(self) -> Path:
        return self.folder / MANIFEST

    def rig_path(self) -> Path:
        p = Path(self.rig)
        return p if p.is_absolute() else (self.folder / p).resolve()

    def to_json(self) -> dict:
        d = {"rig": self.rig, "material": self.material, "complete": self.complete}
        d.update(self.meta)
        d["images"] = [im.to_json() for im in self.images]
        return d

    def save(self) -> None:
        atomic_write_json(self.path, self.to_json())

    def select(self, role: str | None = None, **kw) -> list[ImageEntry]:
        out = []
        for im in self.images:
            if role is not None and im.role != role:
                continue
            if "rotation" in kw and float(im.rotation) != float(kw["rotation"]):
                continue
            if "leds" in kw and im.leds != list(kw["leds"]):
                continue
            out.append(im)
        return out

    def rotations(self) -> list[float]:
        return sorted({im.rotation for im in self.images if im.role == "sequence"})

    def read_raw(self, im: ImageEntry, crop=None):
        """Decode one of this capture's raw files (:func:`glossrig.core.calibration.raw.read_raw`),
        checked against what the manifest recorded: its sha256 (hashed from the same
        bytes that are decoded, so the check costs one pass over data already in
        memory) and its exposure time, ISO and f-number. Every pipeline stage reads
        capture images through here, so a file changed since capture stops with
        "checksum does not match capture.json" naming it, never silently wrong values."""
        from glossrig.core.calibration.raw import read_raw

        return read_raw(self.folder / im.file, crop=crop, exposure_s=im.exposure_s, iso=im.iso,
                        aperture=im.aperture, sha256=im.sha256)

    def kind(self) -> str:
        """What this capture is, from its images' roles: ``"checkerboard"`` (views of
        the checkerboard only: for ``glossrig calibrate camera``), ``"sample"`` (has
        exposure sequences: for extract, calibrate lamps, diagnose) or ``"calibration"``
        (calibration images only), ``"empty"`` when it lists no images."""
        roles = {im.role for im in self.images}
        if "sequence" in roles:
            return "sample"
        if "checkerboard" in roles:
            return "checkerboard"
        if "calibration" in roles:
            return "calibration"
        return "empty"

    def require_sequences(self, what: str, name: str = "SAMPLE_DIR") -> None:
        """Stop early, naming the folder, when this capture has no exposure sequences
        (a checkerboard capture given to extract, say) instead of failing deep inside
        the pipeline. ``what``: the verb that needs them; ``name``: the argument."""
        kind = self.kind()
        if kind == "sample":
            return
        if kind == "checkerboard":
            raise InputError(f"{name} is a checkerboard capture (for glossrig calibrate camera); {what} needs a "
                             f"sample capture with exposure sequences", path=self.folder)
        if kind == "calibration":
            raise InputError(f"{name} holds only calibration images (no exposure sequences); {what} needs a "
                             f"sample capture with exposure sequences", path=self.folder)
        raise InputError(f"{name} lists no images; {what} needs a sample capture with exposure sequences",
                         path=self.folder)

    def verify(self, check_hashes: bool = True) -> None:
        """Every listed file exists (and matches its checksum)."""
        for im in self.images:
            f = self.folder / im.file
            if not f.exists():
                raise InputError("raw file listed in the manifest is missing", path=f)
            if check_hashes and sha256_file(f) != im.sha256:
                raise InputError("checksum does not match capture.json (file changed since capture)", path=f)


def capture_complete(folder: str | Path) -> bool:
    """Whether ``folder`` holds a finished capture: a readable manifest marked complete (a
    capture is marked complete only after its last image is written). False for a missing,
    half-written or unreadable one - the test resumable studies use before re-capturing."""
    try:
        return load_manifest(folder).complete
    except InputError:
        return False


def check_rig_copy(folder: str | Path, rig_bytes: bytes, *, then: str, where: str | Path | None = None,
                   copy: str = RIG_COPY) -> None:
    """Refuse to add to, or to reuse, the capture in ``folder`` unless its copy of the rig description
    (``copy``, default :data:`RIG_COPY`) holds exactly ``rig_bytes``, the rig file the caller works
    with: one capture is taken with one rig. A missing copy is refused too - every capture writes its
    copy before its manifest, so a manifest without it has lost it. The InputError names ``where``
    (default: the copy) and ends with ``then``, what the user can do. The one check of the capture
    orchestrator's resume, ``glossrig simulate``'s checkerboard resume and the studies' reuse of a
    complete capture (``validation.common.check_reuse``)."""
    f = Path(folder) / copy
    try:
        same = f.read_bytes() == rig_bytes
    except OSError:
        same = False
    if not same:
        raise InputError(f"the rig description differs from the capture's copy {f} (or that copy is missing); "
                         f"{then}", path=f if where is None else where)


def load_manifest(folder: str | Path) -> Manifest:
    """The manifest (``capture.json``, :meth:`Manifest.save`) of the capture ``folder``:
    the one reader of the file. Errors name the folder or the file."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not folder.is_dir():
        raise InputError("capture folder not found", path=folder)
    if not path.exists():
        raise InputError("no capture manifest (capture.json) in this folder", path=folder)
    d = read_json(path, "manifest")
    if not isinstance(d, dict):
        raise InputError("manifest is not a JSON object", path=path)
    for k in ("rig", "material", "images"):
        if k not in d:
            raise InputError(f"manifest lacks key {k!r}", path=path)
    if not isinstance(d["images"], list) or not all(isinstance(x, dict) for x in d["images"]):
        raise InputError("manifest images must be a list of objects", path=path)
    images = [ImageEntry.from_json(x, str(path)) for x in d["images"]]
    meta = {k: v for k, v in d.items() if k not in ("rig", "material", "images", "complete")}
    return Manifest(folder=folder, rig=d["rig"], material=d["material"], images=images,
                    complete=bool(d.get("complete", False)), meta=meta)


def read_truth(path: str | Path) -> dict:
    """The twin's ground truth of a simulated capture (``truth.json`` in the capture folder,
    written by :mod:`glossrig.twin.simulate` and the twin camera backend; the pipeline never
    reads it, only evaluations of a measurement do): the one reader of the file. ``path``:
    the file, or the capture folder holding it. Errors name the file."""
    path = Path(path)
    if path.is_dir():
        path = path / TRUTH
    d = read_json(path, TRUTH)
    if not isinstance(d, dict):
        raise InputError(f"{TRUTH} is not a JSON object", path=path)
    return d
