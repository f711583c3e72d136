"""Writing the twin's raw captures as DNG files.

The capture contract (design.md) has the twin write raw files in the format a
real camera could: a DNG (Adobe DNG Specification 1.4) holding the uncompressed
16-bit CFA mosaic, read by the pipeline through rawpy/LibRaw exactly as a real
camera's DNG or NEF would be (:func:`glossrig.core.calibration.raw.read_raw`).

Layout: one IFD0 holding the raw image (NewSubFileType 0, Photometric CFA
32803, CFARepeatPatternDim / CFAPattern, BlackLevelRepeatDim 2x2 + one
BlackLevel per CFA position, WhiteLevel, colour tags) and an EXIF IFD (tag
34665, EXIF 2.32) with ExposureTime, FNumber, ISOSpeedRatings,
DateTimeOriginal, SubSecTimeOriginal and OffsetTimeOriginal, where cameras
put them. ``tifffile`` writes IFD0 but will not write an EXIF IFD, so this
module appends one and patches the pointer to it before the file becomes
visible.

Colour tags: the twin renders linear sRGB/Rec.709 radiance, so its "camera
native" space is linear sRGB scaled per channel by the sensor's sensitivity.
The default ColorMatrix1 is therefore the XYZ(D65) -> linear sRGB matrix of
IEC 61966-2-1 with CalibrationIlluminant1 = D65 (21), and AsShotNeutral
defaults to (1, 1, 1); :meth:`glossrig.twin.sensor.SensorModel.dng_colour`
gives the matching pair for a sensor with unequal channel sensitivities.
The measurement pipeline never uses these tags (it works on raw CFA values);
they only make the files render plausibly in raw viewers.

Writes are atomic (:func:`glossrig.core.atomic.atomic_write`): the file is built in
memory (and hashed there), written under a temporary name in the target folder, fsynced
and then linked/renamed into place, so a reader (or a crash) never sees half a file, and an existing file is
never replaced unless ``overwrite=True``.
"""
from __future__ import annotations

import hashlib
import io
import os
import struct
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import numpy as np
import tifffile

from glossrig.core.atomic import atomic_write_bytes
from glossrig.core.calibration.demosaic import cfa_array
from glossrig.core.errors import InputError

__all__ = ["write_dng", "XYZ_TO_SRGB", "DNG_VERSION"]

DNG_VERSION = (1, 4, 0, 0)
DNG_BACKWARD_VERSION = (1, 1, 0, 0)
#: XYZ (D65) -> linear sRGB, IEC 61966-2-1:1999 (rounded to 4 decimals).
XYZ_TO_SRGB = ((3.2406, -1.5372, -0.4986),
               (-0.9689, 1.8758, 0.0415),
               (0.0557, -0.2040, 1.0570))
ILLUMINANT_D65 = 21

# TIFF field types
_SHORT, _LONG, _RATIONAL, _ASCII, _UNDEFINED = 3, 4, 5, 2, 7
_TAG_EXIF_IFD = 34665
# tifffile refuses to write ExifIFD (34665) itself, so IFD0 gets this unassigned
# code in the same sort position (between CFAPattern 33422 and DNGVersion 50706)
# and the entry's code and value are patched once the EXIF IFD is appended.
_TAG_EXIF_PLACEHOLDER = 34664


def _rational(x: float, limit: int = 1_000_000) -> tuple[int, int]:
    f = Fraction(float(x)).limit_denominator(limit)
    if f.numerator < 0 or f.numerator >= 2 ** 32:
        raise InputError(f"value {x} does not fit a TIFF RATIONAL")
    return f.numerator, f.denominator


def _srational(x: float, den: int = 10000) -> tuple[int, int]:
    return int(round(float(x) * den)), den


def _exif_ifd(entries: list[tuple[int, int, int, bytes]], offset: int) -> bytes:
    """Encode one little-endian TIFF IFD placed at file ``offset`` (even).

    ``entries``: (tag, type, count, packed value bytes). Values longer than 4
    bytes go to a data area right after the IFD, each at an even offset
    (TIFF 6.0, section 2)."""
    entries = sorted(entries)
    n = len(entries)
    data_at = offset + 2 + 12 * n + 4
    head = [struct.pack("<H", n)]
    data = bytearray()
    for tag, typ, count, value in entries:
        if len(value) <= 4:
            head.append(struct.pack("<HHI", tag, typ, count) + value.ljust(4, b"\0"))
        else:
            head.append(struct.pack("<HHII", tag, typ, count, data_at + len(data)))
            data += value
            if len(data) % 2:
                data += b"\0"
    head.append(struct.pack("<I", 0))    # no next IFD
    return b"".join(head) + bytes(data)


def _ascii(s: str) -> tuple[int, bytes]:
    b = s.encode("ascii") + b"\0"
    return len(b), b


def _exif_entries(exposure_s: float, iso: float, aperture: float, time: datetime) -> list:
    ent = []
    num, den = _rational(exposure_s)
    ent.append((33434, _RATIONAL, 1, struct.pack("<II", num, den)))
    num, den = _rational(aperture, 1000)
    ent.append((33437, _RATIONAL, 1, struct.pack("<II", num, den)))
    iso_i = int(round(iso))
    ent.append((34855, _SHORT, 1, struct.pack("<H", min(iso_i, 65535))))
    if iso_i > 65535:   # EXIF 2.3: ISOSpeedRatings saturates; ISOSpeed holds the value
        ent.append((34864, _SHORT, 1, struct.pack("<H", 3)))
        ent.append((34867, _LONG, 1, struct.pack("<I", iso_i)))
    ent.append((36864, _UNDEFINED, 4, b"0232"))
    n, b = _ascii(time.strftime("%Y:%m:%d %H:%M:%S"))
    ent.append((36867, _ASCII, n, b))
    n, b = _ascii(f"{time.microsecond // 1000:03d}")
    ent.append((37521, _ASCII, n, b))
    off = time.utcoffset()
    if off is not None:
        minutes = int(off.total_seconds() // 60)
        sign = "+" if minutes >= 0 else "-"
        n, b = _ascii(f"{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}")
        ent.append((36881, _ASCII, n, b))
    return ent


def _check_inputs(path: Path, mosaic, black_level, white_level, exposure_s, iso, aperture, time):
    a = np.asarray(mosaic)
    if a.ndim != 2 or a.shape[0] < 2 or a.shape[1] < 2:
        raise InputError(f"DNG mosaic must be a 2-D array of at least 2x2, got shape {a.shape}", path=path)
    if a.dtype != np.uint16:
        if not np.issubdtype(a.dtype, np.integer):
            raise InputError(f"DNG mosaic must hold integers (uint16), got {a.dtype}", path=path)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise InputError("DNG mosaic values must lie in [0, 65535]", path=path)
        a = a.astype(np.uint16)
    white = int(white_level)
    if white != white_level or not (0 < white <= 65535):
        raise InputError(f"white_level must be an integer in (0, 65535], got {white_level!r}", path=path)
    black = [int(b) for b in black_level]
    if len(black) != 4 or any(b != bl or not (0 <= b < white) for b, bl in zip(black, black_level)):
        raise InputError(f"black_level must hold 4 integers in [0, white_level), got {tuple(black_level)!r}", path=path)
    for name, v in (("exposure_s", exposure_s), ("iso", iso), ("aperture", aperture)):
        if not (isinstance(v, (int, float, np.number)) and np.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a positive number, got {v!r}", path=path)
    if not isinstance(time, datetime):
        raise InputError(f"time must be a datetime, got {type(time).__name__}", path=path)
    return np.ascontiguousarray(a), black, white


def write_dng(path: str | Path, mosaic: np.ndarray, *, cfa: str = "RGGB",
              black_level: tuple[int, int, int, int], white_level: int,
              exposure_s: float, iso: float, aperture: float, time: datetime,
              make: str = "Nikon", model: str = "D750 (glossrig twin)", unique_model: str | None = None,
              extra_description: str | None = None,
              color_matrix: tuple[tuple[float, float, float], ...] = XYZ_TO_SRGB,
              as_shot_neutral: tuple[float, float, float] = (1.0, 1.0, 1.0),
              overwrite: bool = False) -> str:
    """Write ``mosaic`` (uint16 CFA image, (H, W)) as a DNG; return its sha256.

    ``cfa`` names the 2x2 pattern from the top-left pixel, row by row;
    ``black_level`` gives the black level of each of those four positions in
    the same order (DNG BlackLevelRepeatDim 2x2); ``white_level`` the
    saturation level. Exposure metadata go to the EXIF IFD (see module
    docstring). ``unique_model`` defaults to "<make> <model>". Raises
    :class:`InputError` if ``path`` exists (unless ``overwrite``) or if any
    argument is out of range; nothing is left behind on failure.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("folder for the DNG does not exist", path=path.parent)
    if path.exists() and not overwrite:
        raise InputError("refusing to overwrite an existing file (pass overwrite=True)", path=path)
    pat = cfa_array(cfa)
    data, black, white = _check_inputs(path, mosaic, black_level, white_level, exposure_s, iso, aperture, time)
    cm = np.asarray(color_matrix, float)
    neutral = np.asarray(as_shot_neutral, float)
    if cm.shape != (3, 3) or not np.all(np.isfinite(cm)):
        raise InputError("color_matrix must be a finite 3x3 matrix", path=path)
    if neutral.shape != (3,) or not np.all((neutral > 0) & (neutral <= 1)):
        raise InputError("as_shot_neutral must hold 3 values in (0, 1]", path=path)
    unique = unique_model if unique_model is not None else f"{make} {model}"

    extratags = [
        (254, "I", 1, 0, True),                                     # NewSubFileType: main image
        (271, "s", 0, make, True),
        (272, "s", 0, model, True),
        (274, "H", 1, 1, True),                                     # Orientation: top-left
        (33421, "H", 2, (2, 2), True),                              # CFARepeatPatternDim
        (33422, "B", 4, tuple(int(v) for v in pat.ravel()), True),  # CFAPattern (0=R 1=G 2=B)
        (_TAG_EXIF_PLACEHOLDER, "I", 1, 0, True),                   # becomes ExifIFD, see below
        (50706, "B", 4, DNG_VERSION, True),
        (50707, "B", 4, DNG_BACKWARD_VERSION, True),
        (50708, "s", 0, unique, True),                              # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),                           # CFAPlaneColor: R G B
        (50711, "H", 1, 1, True),                                   # CFALayout: rectangular
        (50713, "H", 2, (2, 2), True),                              # BlackLevelRepeatDim
        (50714, "I", 4, tuple(black), True),                        # BlackLevel, row by row
        (50717, "I", 1, white, True),                               # WhiteLevel
        (50721, "2i", 9, [v for x in cm.ravel() for v in _srational(x)], True),       # ColorMatrix1
        (50728, "2I", 3, [v for x in neutral for v in _rational(x, 10000)], True),    # AsShotNeutral
        (50778, "H", 1, ILLUMINANT_D65, True),                      # CalibrationIlluminant1
    ]
    exif = _exif_entries(float(exposure_s), float(iso), float(aperture), time)

    # The file is built in memory (tifffile's IFD0 and image, then the EXIF IFD appended and
    # pointed to), hashed there and written once: no second pass over the file to patch or hash it.
    buf = io.BytesIO()
    tifffile.imwrite(buf, data, photometric=32803, byteorder="<", bigtiff=False, metadata=None,
                     software="glossrig twin", description=extra_description,
                     datetime=time.strftime("%Y:%m:%d %H:%M:%S"), extratags=extratags)
    buf.seek(0)
    with tifffile.TiffFile(buf) as tf:
        placeholder = tf.pages[0].tags[_TAG_EXIF_PLACEHOLDER]
        entry_at, pointer_at = placeholder.offset, placeholder.valueoffset
    end = buf.seek(0, os.SEEK_END)
    if end % 2:
        buf.write(b"\0")
        end += 1
    if end + 4096 >= 2 ** 32:
        raise InputError("image too large for a classic TIFF/DNG", path=path)
    buf.write(_exif_ifd(exif, end))
    buf.seek(entry_at)
    buf.write(struct.pack("<H", _TAG_EXIF_IFD))
    buf.seek(pointer_at)
    buf.write(struct.pack("<I", end))
    content = buf.getbuffer()
    digest = hashlib.sha256(content).hexdigest()
    try:
        atomic_write_bytes(path, content, overwrite=overwrite)
    except FileExistsError:
        raise InputError("refusing to overwrite an existing file (pass overwrite=True)", path=path) from None
    finally:
        content.release()
    return digest
