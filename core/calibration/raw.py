"""Reading raw captures and linearising them (thesis 4.3.1).

The capture contract (design.md) says raw files - DNG from the twin, NEF or
DNG from a real camera - are read through rawpy/LibRaw, with black and white
levels and exposure metadata taken from the files themselves:

* pixels, CFA pattern, black levels per CFA position and the white
  (saturation) level come from LibRaw (``rawpy``), which also undoes any
  in-camera compression curve while decoding (Nikon NEF curves, DNG
  LinearizationTable) - the "uncompress first" step of thesis 4.3.1;
* exposure time, ISO, f-number and capture time come from the file's EXIF,
  read with ``tifffile`` (DNG and Nikon NEF are TIFF structures; the tags may
  sit in IFD0 as TIFF/EP allows or in the EXIF IFD as cameras write them).
  Values the caller passes (from the capture manifest) are used only when the
  file has none, and are cross-checked when it has.

Everything that is wrong with a file stops with :class:`InputError` naming
the file. Cropping happens right after decoding so full-resolution captures
(6032x4032) can be streamed while keeping only the region of interest.

Demosaicing lives in :mod:`glossrig.core.calibration.demosaic` and is re-exported here.
"""
from __future__ import annotations

import hashlib
import io
import math
import mmap
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from struct import error as struct_error
from typing import Any

import numpy as np
import rawpy
import tifffile

from glossrig.core.calibration.demosaic import CHANNELS, cfa_array, cfa_string, channel_index, demosaic, demosaic_thesis
from glossrig.core.errors import InputError
from glossrig.core.radiometry.hdr import combine_repeats

__all__ = ["RawFrame", "ExifInfo", "read_raw", "read_exif", "linearize", "linearize_mosaic", "linearize_mean", "even_crop",
           "demosaic", "demosaic_thesis", "channel_index", "cfa_array", "cfa_string"]

#: EXIF tag codes used here (EXIF 2.32 / TIFF-EP).
TAG_EXPOSURE_TIME = 33434
TAG_FNUMBER = 33437
TAG_ISO = 34855          # ISOSpeedRatings / PhotographicSensitivity (SHORT, saturates at 65535)
TAG_ISO_SPEED = 34867    # ISOSpeed (LONG), used when the above reads 65535
TAG_DATETIME_ORIGINAL = 36867
TAG_OFFSET_TIME_ORIGINAL = 36881
TAG_SUBSEC_TIME_ORIGINAL = 37521
TAG_EXIF_IFD = 34665
TAG_MAKE = 271
TAG_MODEL = 272
TAG_UNIQUE_CAMERA_MODEL = 50708


@dataclass(frozen=True)
class ExifInfo:
    """Exposure metadata found in a raw file's TIFF/EXIF structure (None = absent)."""

    exposure_s: float | None = None
    iso: float | None = None
    aperture: float | None = None
    timestamp: datetime | None = None
    camera: str | None = None


@dataclass
class RawFrame:
    """One decoded raw capture (or a crop of it), as the pipeline sees it.

    ``mosaic`` is the visible raw CFA image, uint16 (h, w), untouched;
    ``cfa`` the 2x2 colour indices (0=R, 1=G, 2=B) of ``mosaic[0:2, 0:2]``;
    ``black`` the black level LI^b of each of those 2x2 positions (thesis
    4.3.1); ``white`` the saturation level LI^s (one value for all filters).
    ``origin`` is the (x, y) position of ``mosaic[0, 0]`` in the full visible
    image of ``full_size`` (width, height). ``iso``, ``aperture`` and
    ``timestamp`` are None when neither the file nor the caller gave them.
    """

    path: str
    mosaic: np.ndarray
    cfa: np.ndarray
    black: np.ndarray
    white: float
    exposure_s: float
    iso: float | None
    aperture: float | None
    timestamp: datetime | None
    camera: str
    origin: tuple[int, int] = (0, 0)
    full_size: tuple[int, int] = (0, 0)

    @property
    def shape(self) -> tuple[int, int]:
        return self.mosaic.shape

    def channel_index(self) -> np.ndarray:
        """ID^cid (thesis fig. 4.7) for this frame's pixels."""
        return channel_index(self.mosaic.shape, self.cfa)


# --------------------------------------------------------------------- EXIF

def _rational(v) -> float | None:
    """A TIFF RATIONAL as tifffile returns it ((num, den), a number, or a
    sequence of those: the first is taken)."""
    if v is None:
        return None
    if isinstance(v, (tuple, list)):
        if len(v) == 2 and all(isinstance(x, (int, np.integer)) for x in v):
            num, den = v
            return float(num) / float(den) if den else None
        if not v:
            return None
        return _rational(v[0])
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _text(v) -> str | None:
    if v is None:
        return None
    if isinstance(v, bytes):
        v = v.decode("latin-1", "replace")
    s = str(v).strip().strip("\x00").strip()
    return s or None


def _parse_exif_time(dt: str | None, subsec: str | None, offset: str | None) -> datetime | None:
    """EXIF ``YYYY:MM:DD HH:MM:SS`` + SubSecTimeOriginal + OffsetTimeOriginal
    (EXIF 2.31). Unset clocks ("0000:00:00 ...") and malformed strings give None."""
    if not dt:
        return None
    try:
        t = datetime.strptime(dt[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    if subsec and subsec.isdigit():
        t = t.replace(microsecond=int((subsec + "000000")[:6]))
    if offset and len(offset) == 6 and offset[0] in "+-" and offset[3] == ":":
        try:
            h, m = int(offset[1:3]), int(offset[4:6])
        except ValueError:
            return t
        sign = 1 if offset[0] == "+" else -1
        t = t.replace(tzinfo=timezone(sign * timedelta(hours=h, minutes=m)))
    return t


def _exif_lookup(page) -> dict:
    """Tag code -> value from IFD0 and its EXIF IFD (EXIF IFD wins)."""
    out = {}
    for tag in page.tags.values():
        if tag.code != TAG_EXIF_IFD:
            out[tag.code] = tag.value
    exif = page.tags.get(TAG_EXIF_IFD)
    if exif is not None and isinstance(exif.value, dict):
        codes = {name: code for code, name in tifffile.TIFF.TAGS.items()}
        for name, value in exif.value.items():
            code = codes.get(name)
            if code is not None:
                out[code] = value
    return out


#: TIFF/DNG tags that make LibRaw transform the stored CFA values or their frame (DNG 1.6:
#: LinearizationTable, BlackLevelDeltaH/V, ActiveArea, MaskedAreas, DefaultCropOrigin/Size)
_TRANSFORMING_TAGS = (50712, 50715, 50716, 50829, 50830, 50719, 50720)


@dataclass(frozen=True)
class PlainLayout:
    """Where an uncompressed 16-bit CFA image lies in its file: ``offset`` of pixel (0, 0)
    (rows contiguous), ``byteorder`` ('<' or '>'), ``width`` and ``height``; and its
    levels from the DNG tags LibRaw reads them from (``cfa``, ``black`` per 2x2 position,
    ``white``)."""

    offset: int
    byteorder: str
    width: int
    height: int
    cfa: np.ndarray
    black: np.ndarray
    white: float


def _plain_layout(tf) -> PlainLayout | None:
    """The layout of a TIFF/DNG whose one CFA image is stored plainly (uncompressed, 16 bits,
    one sample, strips in order, no tag that LibRaw applies to the values): its pixels
    are the file's bytes, so any crop can be read without decoding the rest. None
    otherwise (compressed NEF or DNG, tiles, SubIFDs, linearisation tables...)."""
    pages = list(tf.pages)
    if len(pages) != 1:
        return None
    p = pages[0]
    if (getattr(p, "subifds", None) or p.is_tiled or int(p.photometric) != 32803 or int(p.compression) != 1
            or p.bitspersample != 16 or p.samplesperpixel != 1 or int(p.tags.valueof(254, 0) or 0) != 0
            or 50706 not in p.tags or any(code in p.tags for code in _TRANSFORMING_TAGS)):     # 50706: DNGVersion
        return None
    offs, counts = [int(o) for o in p.dataoffsets], [int(c) for c in p.databytecounts]
    h, w = int(p.imagelength), int(p.imagewidth)
    if not offs or any(o + c != n for o, c, n in zip(offs, counts, offs[1:])) or sum(counts) != w * h * 2:
        return None
    # DNG 1.6 tags: CFARepeatPatternDim 33421, CFAPattern 33422, CFAPlaneColor 50710,
    # BlackLevelRepeatDim 50713, BlackLevel 50714, WhiteLevel 50717
    v = p.tags.valueof
    planes = tuple(v(50710, (0, 1, 2)))
    pattern = v(33422)
    if tuple(v(33421, ())) != (2, 2) or pattern is None or len(pattern) != 4 or planes != (0, 1, 2):
        return None
    cfa = np.array([int(c) for c in pattern], np.int8).reshape(2, 2)
    if sorted(cfa.ravel().tolist()) != [0, 1, 1, 2]:
        return None
    dim = tuple(v(50713, (1, 1)))
    if dim not in ((1, 1), (2, 2)) or any(code in p.tags and int(p.tags[code].dtype) not in (3, 4)
                                          for code in (50714, 50717)):
        return None             # levels as RATIONAL (or odd repeats): LibRaw's reading is used
    levels = np.atleast_1d(np.asarray(v(50714, 0), np.float64)).ravel()
    white = np.atleast_1d(np.asarray(v(50717, 65535), np.float64)).ravel()
    if levels.size != dim[0] * dim[1] or white.size != 1:
        return None
    black = np.broadcast_to(levels.astype(np.float32).reshape(dim), (2, 2)).copy()
    return PlainLayout(offs[0], tf.byteorder, w, h, cfa, black, float(white[0]))


def _tiff_info(path: Path, data=None) -> tuple[ExifInfo, str | None, str | None, PlainLayout | None]:
    """EXIF info from the TIFF structure, plus two diagnoses: ``truncated``
    (the image data runs past the end of the file: certainly broken) and
    ``unparsed`` (tifffile could not read the structure: the file may still
    be a raw format LibRaw knows, so only LibRaw's verdict is final), and the
    :class:`PlainLayout` of a plainly stored CFA image (else None).
    ``data``: the file's contents when the caller has them already, as ``bytes`` or
    mapped (:func:`_mapped`), so its structure is parsed from them and not read again."""
    size = path.stat().st_size if data is None else len(data)
    layout = None
    # tifffile's pages keep their file handle in reference cycles, which only the garbage
    # collector frees: a buffer over bytes is closed here so the file's bytes are not kept
    # alive with them (measured: ~33 MB per file otherwise, until a collection); a map is
    # read in place and closed by its owner (_mapped), whatever still refers to it
    src: Any = path if data is None else data if isinstance(data, mmap.mmap) else io.BytesIO(data)
    try:
        with tifffile.TiffFile(src) as tf:
            tags = _exif_lookup(tf.pages[0])
            # Truncation check: every strip/tile of every IFD (and SubIFD) must
            # lie inside the file. LibRaw notices too, but says only "I/O error".
            stack = list(tf.pages)
            while stack:
                page = stack.pop()
                offs, counts = page.dataoffsets, page.databytecounts
                if offs and counts:
                    end = max(int(o) + int(c) for o, c in zip(offs, counts))
                    if end > size:
                        return ExifInfo(), (f"file is truncated: image data runs to byte {end} "
                                            f"but the file has only {size} bytes"), None, None
                if getattr(page, "subifds", None):
                    stack.extend(page.pages or ())     # not None: the page has SubIFDs
            layout = _plain_layout(tf)
    except tifffile.TiffFileError as e:
        if str(e).startswith("not a TIFF"):   # another raw container (CR3, RAF...): LibRaw decides
            return ExifInfo(), None, None, None
        return ExifInfo(), None, f"corrupt TIFF structure ({e})", None
    except (ValueError, TypeError, IndexError, KeyError, OSError, struct_error) as e:
        return ExifInfo(), None, f"unreadable TIFF structure ({type(e).__name__}: {e})", None
    finally:
        if isinstance(src, io.BytesIO):
            src.close()
    iso = tags.get(TAG_ISO)
    if isinstance(iso, (tuple, list)):
        iso = iso[0] if iso else None
    if iso is not None and int(iso) == 65535 and tags.get(TAG_ISO_SPEED):
        iso = tags.get(TAG_ISO_SPEED)
    make, model = _text(tags.get(TAG_MAKE)), _text(tags.get(TAG_MODEL))
    camera = _text(tags.get(TAG_UNIQUE_CAMERA_MODEL))
    if camera is None and (make or model):
        camera = model if (make and model and model.startswith(make)) else " ".join(x for x in (make, model) if x)
    exposure = _rational(tags.get(TAG_EXPOSURE_TIME))
    fnum = _rational(tags.get(TAG_FNUMBER))
    info = ExifInfo(
        exposure_s=exposure if exposure and exposure > 0 else None,
        iso=float(iso) if iso else None,
        aperture=fnum if fnum and fnum > 0 else None,
        timestamp=_parse_exif_time(_text(tags.get(TAG_DATETIME_ORIGINAL)), _text(tags.get(TAG_SUBSEC_TIME_ORIGINAL)),
                                   _text(tags.get(TAG_OFFSET_TIME_ORIGINAL))),
        camera=camera)
    return info, None, None, layout


def read_exif(path: str | Path) -> ExifInfo:
    """Exposure time, ISO, f-number, capture time and camera name of a raw
    file's TIFF/EXIF structure (fields are None where absent)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("raw file not found", path=path)
    info, truncated, unparsed, _ = _tiff_info(path)
    problem = truncated or unparsed
    if problem:
        raise InputError(problem, path=path)
    return info


# ---------------------------------------------------------------- reading

def even_crop(box: tuple[int, int, int, int], size: tuple[int, int]) -> tuple[int, int, int, int]:
    """Grow ``box`` = (x0, y0, x1, y1) (half-open pixel window) to whole 2x2
    CFA tiles - even x0, y0, x1, y1 - and clip it to ``size`` = (width,
    height), so the crop keeps the CFA phase of the full image."""
    x0, y0, x1, y1 = (int(v) for v in box)
    w, h = int(size[0]), int(size[1])
    x0, y0 = max(0, x0 - x0 % 2), max(0, y0 - y0 % 2)
    x1, y1 = min(w, x1 + x1 % 2), min(h, y1 + y1 % 2)
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"crop {box} does not overlap the image of size {w}x{h}")
    return x0, y0, x1, y1


def _check_crop(crop, w: int, h: int, path: Path) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(v) for v in crop)
    except (TypeError, ValueError):
        raise InputError(f"crop must be (x0, y0, x1, y1), got {crop!r}", path=path) from None
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise InputError(f"crop {(x0, y0, x1, y1)} is outside the {w}x{h} image", path=path)
    if x0 % 2 or y0 % 2:
        raise InputError(f"crop {(x0, y0, x1, y1)} starts at an odd offset, which would shift the CFA phase; "
                         f"use even x0 and y0 (glossrig.core.calibration.raw.even_crop)", path=path)
    return x0, y0, x1, y1


def _agree(name: str, from_file: float | None, given: float | None, rel_tol: float, path: Path) -> float | None:
    """The file's value wins; the caller's (manifest) value fills a gap and
    must agree with the file's within ``rel_tol``."""
    if given is not None:
        given = float(given)
        if not (math.isfinite(given) and given > 0):
            raise InputError(f"{name} given for this file must be > 0, got {given}", path=path)
    if from_file is None:
        return given
    if given is not None and abs(from_file - given) > rel_tol * max(abs(from_file), abs(given)):
        raise InputError(f"{name} in the file's EXIF ({from_file:g}) disagrees with the expected value ({given:g}); "
                         f"the file may belong to another shot", path=path)
    return from_file


def read_raw(path: str | Path, crop: tuple[int, int, int, int] | None = None, *,
             exposure_s: float | None = None, iso: float | None = None, aperture: float | None = None,
             timestamp: datetime | None = None, rel_tol: float = 0.1, sha256: str | None = None) -> RawFrame:
    """Decode a raw file (DNG, NEF, ... anything LibRaw reads with a 2x2
    Bayer CFA) into a :class:`RawFrame`.

    ``crop`` = (x0, y0, x1, y1), a half-open window of the visible image with
    even x0 and y0 (so ``cfa`` and ``black`` stay those of the full image);
    only that window is kept in memory. ``exposure_s``, ``iso``,
    ``aperture`` and ``timestamp`` are the manifest's values: used when the
    file's EXIF lacks them, otherwise checked against it (relative tolerance
    ``rel_tol``; 10 % catches a shot off by a third of a stop while letting
    1/60 s stand for the table's 0.0166 s). A file with no exposure time,
    and none given, is an error: HDR merging (thesis 4.3.3) needs it.

    ``sha256``: the checksum the capture manifest recorded for this file. The
    file is then hashed and decoded from one read-only mapping of it (:func:`_mapped`),
    so a file changed since capture (a flipped byte decodes silently into wrong pixel
    values) stops here instead of reaching the results. (A file rewritten in place by
    another program between the hash and the decode is not excluded by a mapping as it
    would be by a private copy; the capture tools replace files atomically.) :meth:`glossrig.core.capture.Manifest.read_raw` passes it for every
    capture image.

    The mosaic is in sensor orientation: the file's orientation flag is not
    applied (the rig's geometry is calibrated in sensor pixels).

    The crop is taken as early as the format allows: a DNG whose CFA image is stored
    plainly (uncompressed 16-bit strips, no linearisation table, active area or black
    deltas: :class:`PlainLayout`, the twin's DNGs) has the crop's rows (all rows without
    ``crop``) copied from the mapped file and its levels from the DNG tags LibRaw reads
    them from, with values equal to LibRaw's decode (tests/test_extract_parallel.py);
    anything else is decoded whole by LibRaw and cropped right after.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("raw file not found", path=path)
    if path.stat().st_size == 0:
        raise InputError("raw file is empty", path=path)
    with _mapped(path) as data:
        if sha256 is not None and hashlib.sha256(data).hexdigest() != str(sha256).lower():
            raise InputError("checksum does not match capture.json (file changed since capture)", path=path)
        info, truncated, unparsed, layout = _tiff_info(path, data)
        if truncated:
            raise InputError(truncated, path=path)
        if layout is not None:
            # A plainly stored DNG (PlainLayout): the crop's rows are copied from the mapped
            # file, the levels taken from the tags LibRaw reads them from; the other rows are
            # never touched. tests/test_extract_parallel.py checks it equals LibRaw's reading.
            w, h = layout.width, layout.height
            x0, y0, x1, y1 = _check_crop((0, 0, w, h) if crop is None else crop, w, h, path)
            mosaic = _plain_crop(data, layout, (x0, y0, x1, y1))
            cfa, black, white = layout.cfa.copy(), layout.black.copy(), layout.white
        else:
            cfa, black, white, mosaic, (x0, y0), (w, h) = _read_libraw(path, data, crop, unparsed)
    if not (white > float(black.max())):
        raise InputError(f"white level {white:g} is not above the black levels {black.ravel().tolist()}", path=path)
    exp = _agree("exposure time", info.exposure_s, exposure_s, rel_tol, path)
    if exp is None:
        why = f" ({unparsed})" if unparsed else ""
        raise InputError(f"no exposure time in the file's EXIF{why} and none given by the caller", path=path)
    return RawFrame(
        path=str(path), mosaic=mosaic, cfa=cfa, black=black, white=white, exposure_s=exp,
        iso=_agree("ISO", info.iso, iso, rel_tol, path),
        aperture=_agree("f-number", info.aperture, aperture, rel_tol, path),
        timestamp=info.timestamp if info.timestamp is not None else timestamp,
        camera=info.camera or "unknown camera", origin=(x0, y0), full_size=(w, h))


@contextmanager
def _mapped(path: Path):
    """The file's contents, mapped read-only (closed on exit), with the kernel asked to read
    all of it ahead: hashing, parsing and cropping then read the file's pages once, in
    place, without a 48 MB copy per full-resolution plainly stored DNG nor the page faults of
    a fresh buffer (measured: 42 against 71 ms of CPU per file for checksum, tags and crop;
    issue 19; compressed raws decoded by LibRaw are still copied into its buffer). Where the
    file cannot be mapped, its bytes."""
    try:
        with open(path, "rb") as f:
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):
        yield path.read_bytes()
        return
    try:
        if hasattr(data, "madvise"):
            data.madvise(mmap.MADV_WILLNEED)
        yield data
    finally:
        try:
            data.close()
        except BufferError:         # a view still held (by an exception's frames): unmapped when it goes
            pass


def _plain_crop(data, layout: PlainLayout, box: tuple[int, int, int, int]) -> np.ndarray:
    """The window ``box`` (checked, even origin) of a plainly stored CFA image, copied out of
    ``data`` as native uint16 (the view into ``data`` ends with this call)."""
    x0, y0, x1, y1 = box
    w = layout.width
    rows = np.frombuffer(data, np.dtype("<u2" if layout.byteorder == "<" else ">u2"), (y1 - y0) * w,
                         layout.offset + 2 * y0 * w).reshape(y1 - y0, w)
    return rows[:, x0:x1].astype(np.uint16)


def _read_libraw(path: Path, data, crop, unparsed: str | None):
    """Decode with LibRaw (rawpy): CFA, black levels, white level, the (cropped) visible
    mosaic, its origin and the visible image's (width, height)."""
    try:
        with rawpy.imread(str(path) if data is None else io.BytesIO(data)) as raw:
            pattern = raw.raw_pattern
            desc = raw.color_desc.decode("ascii", "replace")
            if pattern is None or pattern.shape != (2, 2) or raw.num_colors != 3:
                raise InputError(f"not a 2x2 Bayer CFA raw image (LibRaw colours {desc!r}, pattern "
                                 f"{None if pattern is None else pattern.tolist()})", path=path)
            letters = [desc[int(i)] for i in pattern.ravel()]
            if sorted(letters) != sorted("RGGB"):
                raise InputError(f"CFA {''.join(letters)!r} is not a red/green/blue Bayer pattern", path=path)
            cfa = np.array([CHANNELS.index(ch) for ch in letters], np.int8).reshape(2, 2)
            blpc = list(raw.black_level_per_channel)
            black = np.array([[blpc[int(pattern[i, j])] for j in range(2)] for i in range(2)], np.float32)
            white = float(raw.white_level)
            vis = raw.raw_image_visible
            h, w = vis.shape
            if crop is None:
                x0, y0, x1, y1 = 0, 0, w, h
            else:
                x0, y0, x1, y1 = _check_crop(crop, w, h, path)
            mosaic = np.array(vis[y0:y1, x0:x1], dtype=np.uint16, copy=True)
    except rawpy.LibRawError as e:
        msg = e.args[0].decode("utf-8", "replace") if e.args and isinstance(e.args[0], bytes) else str(e)
        why = f"; {unparsed}" if unparsed else ""
        raise InputError(f"not a readable raw file (LibRaw: {msg}{why})", path=path) from None
    return cfa, black, white, mosaic, (x0, y0), (w, h)


# ------------------------------------------------------------- linearising

def linearize_mosaic(mosaic: np.ndarray, black, white: float) -> np.ndarray:
    """Thesis eq. 4.1-4.2: CI^lin = clip((CI^raw - LI^b) / (LI^s - LI^b), 0, 1).

    ``black`` is a scalar or the 2x2 black levels of the CFA positions of
    ``mosaic[0:2, 0:2]``; ``white`` the saturation level. Returns float32.

    The thesis prints min(max(x, 1.0), 0.0), which is 0 for every x; the
    intended (and here implemented) clipping is min(max(x, 0.0), 1.0). Pixels
    at or above the white level give exactly 1.0 (the division of equal
    integers is exact), which the HDR step uses to recognise saturation.
    """
    m = np.asarray(mosaic)
    if m.ndim != 2:
        raise InputError(f"linearize expects a 2-D CFA mosaic, got shape {m.shape}")
    b = np.broadcast_to(np.asarray(black, np.float32), (2, 2))
    if not float(white) > float(b.max()):
        raise InputError(f"white level {white} must exceed the black levels {b.ravel().tolist()}")
    out = m.astype(np.float32)   # the one float copy
    for i in range(2):
        for j in range(2):
            plane = out[i::2, j::2]
            plane -= b[i, j]
            plane /= np.float32(white) - b[i, j]
    np.clip(out, 0.0, 1.0, out=out)
    return out


def linearize(frame: RawFrame) -> np.ndarray:
    """Linearised mosaic of a :class:`RawFrame` in [0, 1] (thesis eq. 4.1-4.2;
    see :func:`linearize_mosaic` for the clipping fix)."""
    return linearize_mosaic(frame.mosaic, frame.black, frame.white)


def linearize_mean(mosaics, black, white: float) -> tuple[np.ndarray, np.ndarray]:
    """Thesis eq. 4.1-4.2 and 4.31 fused: the mean of the linearised repeats of one
    exposure, ``mean_i clip((CI_i - LI^b) / (LI^s - LI^b), 0, 1)``, and where a repeat
    was saturated (at or above the white level ``white``).

    ``mosaics``: the m repeats, 2-D CFA mosaics of one shape with ``black`` (a scalar or
    the 2x2 black levels of ``mosaic[0:2, 0:2]``) and ``white`` as in
    :func:`linearize_mosaic`. Returns ``(mean, saturated)``: float32 and bool, the
    mosaics' shape.

    Integer raw values with integer levels (every raw format LibRaw decodes) are
    clipped to [LI^b, LI^s] and summed as integers, which is exact; the one division,
    (sum - m LI^b) / (m (LI^s - LI^b)), is done in float32 (all integers involved are
    below 2^24, so exact there) and rounded once: the result is the correctly rounded
    mean, a relative error of at most 2^-24 = 6e-8. The separate route, a float32
    linearised frame per repeat (one rounding each) averaged in float64 and rounded to
    float32 (:func:`linearize_mosaic` then
    :func:`glossrig.core.radiometry.hdr.combine_repeats`), differs from it by at most
    one float32 unit in the last place (1.2e-7 relative), while the shot noise of one
    frame is above 1e-3 relative wherever the HDR step uses it (> 0.002 of the range,
    about 20 electrons at ISO 320): the error budget is 1e-4 of the noise. A value at
    or above the white level gives exactly 1.0 as in :func:`linearize_mosaic`. Other
    inputs (float mosaics, fractional levels) take that separate route itself:
    :func:`~glossrig.core.radiometry.hdr.combine_repeats` fed the linearised repeats by a
    generator, one repeat at a time. One pass over m uint16 frames instead of m float32
    frames and their float64 mean: no (m, H, W) array is made on either route.
    """
    mos = [np.asarray(x) for x in mosaics]
    if not mos:
        raise InputError("linearize_mean: no mosaics given")
    shape = mos[0].shape
    if len(shape) != 2 or any(x.shape != shape for x in mos):
        raise InputError(f"linearize_mean expects 2-D CFA mosaics of one shape, got {[x.shape for x in mos]}")
    b = np.broadcast_to(np.asarray(black, np.float64), (2, 2))
    wl = float(white)
    if not wl > float(b.max()):
        raise InputError(f"white level {white} must exceed the black levels {b.ravel().tolist()}")
    m = len(mos)
    exact = (all(x.dtype in (np.uint8, np.uint16) for x in mos) and np.all(b == np.round(b)) and wl.is_integer()
             and 0 <= float(b.min()) and m * wl < 2 ** 24)
    if not exact:       # linearised one repeat at a time (a generator): one float32 frame in memory
        mean, sat = combine_repeats(linearize_mosaic(x, black, white)[None] for x in mos)
        return mean[0], sat[0]
    bi = b.astype(np.int64)
    uniform = bool(np.all(bi == bi[0, 0]))       # one black level: scalar bounds on the whole mosaic
    total = np.zeros(shape, np.uint32)
    sat = np.zeros(shape, bool)
    lo_full = None
    for x in mos:
        top = min(int(wl), int(np.iinfo(x.dtype).max))
        if uniform:
            np.add(total, np.clip(x, x.dtype.type(bi[0, 0]), x.dtype.type(top)), out=total)
        else:
            if lo_full is None or lo_full.dtype != x.dtype:
                lo_full = np.tile(bi.astype(x.dtype), (-(-shape[0] // 2), -(-shape[1] // 2)))[:shape[0], :shape[1]]
            np.add(total, np.clip(x, lo_full, x.dtype.type(top)), out=total)
        if wl <= np.iinfo(x.dtype).max:             # else no value of this type reaches the white level
            sat |= x >= top
    out = total.astype(np.float32)
    # (sum - m LI^b) / (m (LI^s - LI^b)) per CFA position (all at once for one level), in float32
    for i, j in [(0, 0)] if uniform else [(0, 0), (0, 1), (1, 0), (1, 1)]:
        plane = out if uniform else out[i::2, j::2]
        plane -= np.float32(m * bi[i, j])
        plane /= np.float32(m * (wl - bi[i, j]))
    return out, sat
