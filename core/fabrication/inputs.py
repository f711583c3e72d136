"""The input image: grey -> coverage in [0, 1], resampled onto the halftone grid (thesis 5.2).

Thesis 5.2: "As input, we take a grayscale image with different gray values in the range
between 0 and 1. Here, the gray value denotes the line coverage": 0 leaves the glossy
sheet untouched, 1 scratches it fully. Integer images are scaled by their type's full
range (8 bit: /255, 16 bit: /65535); float images must already lie in [0, 1]. Colour
images are converted to luma (ITU-R 601-2, Pillow's ``convert("L")``:
L = 0.299 R + 0.587 G + 0.114 B on the stored, gamma-encoded values), with a warning
when the image really has colour (:func:`colour_spread`: more than
:data:`COLOUR_PIXEL_SHARE` of its pixels have channels differing by more than
:data:`COLOUR_TOLERANCE`, which JPEG's chroma noise on a grey picture stays below);
images with transparent pixels are refused (a coverage for "nothing here" is undefined).

Resampling to the grid is linear in the image's value, which is correct for coverages
(the scratched area of a region is the mean of its coverages) and for effective
coverages, whose BRDF mix (eq. 6.3) is linear too; the ETN is therefore applied after
resampling.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from glossrig.core.errors import InputError

_log = logging.getLogger(__name__)

#: channel difference (of 255) below which a pixel counts as grey
COLOUR_TOLERANCE = 4
#: share of pixels that must exceed the tolerance for an image to count as coloured
COLOUR_PIXEL_SHARE = 0.001
LUMA_WEIGHTS = (0.299, 0.587, 0.114)          # ITU-R BT.601, as Pillow's convert("L")


def colour_spread(im: Image.Image) -> tuple[float, float]:
    """(largest channel difference of any pixel, of 255; share of pixels whose channels
    differ by more than :data:`COLOUR_TOLERANCE`) of a Pillow image, as RGB."""
    rgb = np.asarray(im.convert("RGB"), dtype=np.int16)
    spread = rgb.max(axis=-1) - rgb.min(axis=-1)
    return float(spread.max()), float(np.mean(spread > COLOUR_TOLERANCE))


def load_coverage_image(path: str | Path) -> np.ndarray:
    """Read ``path`` as a float64 ``(rows, cols)`` image in [0, 1] (module docstring)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in im.info):
                alpha = np.asarray(im.convert("RGBA"))[..., 3]
                if alpha.min() < 255:
                    raise InputError(f"image has transparent pixels ({mode}); coverage is undefined there", path=path)
            if mode in ("1", "L", "P", "RGB", "RGBA", "LA", "PA", "CMYK", "YCbCr", "LAB", "HSV"):
                if mode not in ("1", "L", "LA"):
                    top, share = colour_spread(im)
                    if share > COLOUR_PIXEL_SHARE:
                        w = LUMA_WEIGHTS
                        _log.warning(f"{path.name} is a colour image ({mode}; {share:.1%} of its pixels have channels "
                                     f"differing by more than {COLOUR_TOLERANCE}/255, up to {top:.0f}/255): it is "
                                     f"turned grey as luma L = {w[0]} R + {w[1]} G + {w[2]} B (ITU-R BT.601, on the "
                                     f"stored gamma-encoded values), and only that grey is printed as coverage")
                arr = np.asarray(im.convert("L"), dtype=np.float64) / 255.0
            elif mode.startswith("I;16"):
                arr = np.asarray(im, dtype=np.float64) / 65535.0
            elif mode == "I":
                raw = np.asarray(im, dtype=np.float64)
                if raw.min() < 0 or raw.max() > 65535:
                    raise InputError(f"32-bit integer image with values {raw.min():g}..{raw.max():g}; "
                                     "expected 0..65535 (16-bit grey)", path=path)
                arr = raw / 65535.0
            elif mode == "F":
                arr = np.asarray(im, dtype=np.float64)
                if not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
                    raise InputError("float image must hold finite coverages in [0, 1]", path=path)
            else:
                raise InputError(f"image mode {mode!r} cannot be converted to grey", path=path)
    except FileNotFoundError:
        raise InputError("image not found", path=path) from None
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError, SyntaxError) as e:
        raise InputError(f"not a readable image (needs a greyscale-convertible format): {e}", path=path) from None
    if arr.ndim != 2 or arr.size == 0:
        raise InputError(f"image has shape {arr.shape}; expected a non-empty 2-D grey image", path=path)
    return arr


def resample(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``image`` on a ``(rows, cols)`` grid: area average when shrinking, bilinear when growing."""
    image = np.asarray(image, dtype=np.float64)
    if image.shape == tuple(shape):
        return image.copy()
    rows, cols = shape
    shrink = rows * cols < image.shape[0] * image.shape[1]
    out = cv2.resize(image, (cols, rows), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return np.clip(out, 0.0, 1.0)
