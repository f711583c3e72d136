"""Colour filter array helpers and demosaicing of the calibration image.

Thesis 4.3.2 ("Demosaicing"): the calibration image CI^lin is turned into an
RGB image CI^rgb; the sequence images are never demosaiced (their CFA values
are used as they are). Colour indices follow the thesis (fig. 4.7): 0 = red,
1 = green (both greens), 2 = blue.

Two implementations:

* :func:`demosaic` - the project's default. OpenCV's bilinear Bayer
  demosaicing (``cv2.demosaicing``), as design.md asks. Interior pixels agree
  with the thesis's kernels (eq. 4.4-4.5); at the image border OpenCV
  extrapolates from the pixels that exist, whereas the thesis pads with zeros
  and so darkens the outermost row and column by up to a factor of 2-4. This
  departure is deliberate; ``tests/test_dng_raw.py`` shows the border gain.
* :func:`demosaic_thesis` - eq. 4.3-4.5 exactly as printed (split into
  per-colour planes, convolve with K_c, zero padding of 1). Kept for
  reproducing the thesis and for comparison.
"""
from __future__ import annotations

import cv2
import numpy as np

from glossrig.core.errors import InputError

#: Letters of the colour indices (thesis fig. 4.7).
CHANNELS = "RGB"


def cfa_array(cfa) -> np.ndarray:
    """A 2x2 CFA as an int8 array of colour indices (0=R, 1=G, 2=B).

    ``cfa`` is a four-letter Bayer string read row by row (``"RGGB"``: R at
    (0,0), G at (0,1) and (1,0), B at (1,1)) or anything array-like of shape
    (2,2) holding colour indices.
    """
    if isinstance(cfa, str):
        s = cfa.upper()
        if len(s) != 4 or sorted(s) != sorted("RGGB"):
            raise InputError(f"CFA must be a 2x2 Bayer pattern such as 'RGGB', got {cfa!r}")
        return np.array([CHANNELS.index(ch) for ch in s], dtype=np.int8).reshape(2, 2)
    a = np.asarray(cfa)
    if a.shape != (2, 2) or sorted(a.ravel().tolist()) != [0, 1, 1, 2]:
        raise InputError("CFA must be a 2x2 array holding one red (0), two green (1) and one blue (2), "
                         f"got {a.tolist()}")
    return a.astype(np.int8)


def cfa_string(cfa) -> str:
    """The four-letter name (``"RGGB"``...) of a CFA given as string or array."""
    return "".join(CHANNELS[i] for i in cfa_array(cfa).ravel())


def channel_index(shape: tuple[int, int], cfa) -> np.ndarray:
    """ID^cid of thesis 4.3.2 / fig. 4.7: the colour index (0=R, 1=G, 2=B)
    of every pixel of a mosaic of ``shape`` (H, W) whose pixel (0,0) sits at
    CFA position (0,0). Returns an int8 (H, W) array (a view-free tile)."""
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1:
        raise InputError(f"channel_index: shape must be positive, got {shape}")
    pat = cfa_array(cfa)
    return np.tile(pat, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def _check_mosaic(linear: np.ndarray) -> np.ndarray:
    a = np.asarray(linear)
    if a.ndim != 2:
        raise InputError(f"demosaic expects a 2-D CFA mosaic, got shape {a.shape}")
    if a.shape[0] < 2 or a.shape[1] < 2:
        raise InputError(f"demosaic needs at least a 2x2 mosaic, got shape {a.shape}")
    return a


def demosaic(linear: np.ndarray, cfa) -> np.ndarray:
    """Bilinear demosaicing of a CFA mosaic with OpenCV -> (H, W, 3) RGB.

    Thesis 4.3.2, eq. 4.3-4.5 (bilinear interpolation of the missing colours),
    computed by ``cv2.demosaicing`` with the ``COLOR_Bayer<CFA>2RGB`` code of
    OpenCV 5, whose names give the 2x2 pattern from the top-left pixel (the
    channel order is checked on synthetic mosaics in the tests). Differs from
    the printed method only at the border (see module docstring).

    ``linear`` is float (e.g. :func:`glossrig.core.calibration.raw.linearize` output, in
    [0, 1]) or uint16/uint8. Float input is quantised to 16 bits for OpenCV
    (steps of 1/65535 of the input range, well below a 14-bit sensor's step)
    and returned as float32 in the same scale; integer input keeps its dtype.
    """
    a = _check_mosaic(linear)
    code = getattr(cv2, f"COLOR_Bayer{cfa_string(cfa)}2RGB")
    if a.dtype in (np.uint8, np.uint16):
        return cv2.demosaicing(np.ascontiguousarray(a), code)
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(f"demosaic: unsupported dtype {a.dtype} (use float, uint8 or uint16)")
    lo, hi = float(np.min(a)), float(np.max(a))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise InputError("demosaic: the mosaic holds NaN or infinite values")
    lo = min(lo, 0.0)
    scale = (hi - lo) if hi > lo else 1.0
    q = np.empty(a.shape, np.uint16)
    np.rint((a - lo) * (65535.0 / scale), out=q, casting="unsafe")
    rgb = cv2.demosaicing(q, code).astype(np.float32)
    rgb *= np.float32(scale / 65535.0)
    if lo != 0.0:
        rgb += np.float32(lo)
    return rgb


#: Thesis eq. 4.5: kernels for red/blue (K_0 = K_2) and for green (K_1).
K_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32) / 4.0
K_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], np.float32) / 4.0


def demosaic_thesis(linear: np.ndarray, cfa) -> np.ndarray:
    """Thesis eq. 4.3-4.5 as printed: CI^col_c = CI^lin where ID^cid = c, else
    0 (eq. 4.3); CI^rgb_c = K_c * CI^col_c (eq. 4.4) with the kernels of
    eq. 4.5, stride 1 and zero padding of 1. Returns float32 (H, W, 3).

    The zero padding darkens the border pixels; :func:`demosaic` avoids that.
    """
    a = _check_mosaic(linear).astype(np.float32, copy=False)
    cid = channel_index(a.shape, cfa)
    out = np.empty(a.shape + (3,), np.float32)
    for c, k in ((0, K_RB), (1, K_G), (2, K_RB)):
        plane = np.where(cid == c, a, np.float32(0))
        # The kernels are symmetric, so correlation (filter2D) == convolution.
        out[..., c] = cv2.filter2D(plane, cv2.CV_32F, k, borderType=cv2.BORDER_CONSTANT)
    return out
