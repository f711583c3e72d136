"""Patch normalisation of an HDR mosaic (thesis 4.3.3 "Patch Normalization", eq. 4.45-4.50).

The LED's slow drift (and whatever image-wide gain neighbour correction
leaves, :func:`glossrig.core.radiometry.hdr.neighbour_correct`) is removed by dividing
the HDR image by the mean of the white patch of the holder's marker, which
every image sees under the same LED. Eq. 4.45-4.48 build the patch mask from
the marker contour (dilate the contour line with a 70x70 kernel, subtract it
from the filled contour); that is the marker detector's job
(:mod:`glossrig.core.calibration.marker_detect`), so here the mask is an input.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from glossrig.core.calibration.demosaic import CHANNELS, channel_index
from glossrig.core.errors import InputError

__all__ = ["PatchResult", "normalise_by_patch"]


@dataclass
class PatchResult:
    """``image`` float32 (H, W): the HDR mosaic divided by the patch mean of
    its pixel's CFA channel (NaN stays NaN); ``variance`` the input variance
    divided by the square of that mean (None when none was given);
    ``scale`` (3,) the divisor per channel R, G, B; ``pixels`` (3,) the
    patch pixels of each channel that entered the mean."""

    image: np.ndarray
    variance: np.ndarray | None
    scale: np.ndarray
    pixels: np.ndarray


def normalise_by_patch(hdr, patch_mask, cfa, *, variance=None, method: str = "per_channel",
                       max_invalid_fraction: float = 0.1, name: str = "HDR image") -> PatchResult:
    """Divide an HDR CFA mosaic by the mean of the marker's white patch
    (thesis eq. 4.49-4.50) so that the patch averages 1.

    ``hdr`` (H, W): rates from :func:`glossrig.core.radiometry.hdr.hdr_ml` (NaN =
    unknown); ``patch_mask`` bool (H, W): the white patch's pixels (CI^ic,
    eq. 4.48); ``cfa``: the 2x2 pattern of ``hdr[0:2, 0:2]`` ("RGGB" or
    colour indices); ``variance`` (H, W) optional, scaled alike.

    ``method="per_channel"`` (default): each CFA colour (R, G and B
    positions) is divided by the patch mean of that colour, so after
    normalisation the white patch is 1 in every channel and neither the
    LED's colour nor the camera's channel sensitivities tint the result:
    values become reflectance relative to the white patch, per channel.
    This departs from the thesis, whose single average mixes the channels
    of the mosaic, so a colour LED leaves the normalised image tinted.
    ``method="thesis"``: that single average over all patch pixels.

    Eq. 4.49 as printed, avg = (1 / (h w)) sum over *all* pixels of
    SI^hdr, is the mean of the whole image, not of the patch; the text
    ("the average of the inner pixels") and eq. 4.48 show the sum is meant
    to run over the patch CI^ic and the divisor to be its pixel count, which
    both methods implement.

    Patch pixels with a NaN rate (saturated at every exposure, or outside
    the measured range) are left out of the mean; if more than
    ``max_invalid_fraction`` of a channel's patch pixels are NaN the mean
    would be biased (the brightest pixels are the ones lost), so it is an
    :class:`InputError`, as is an empty patch, a mask of the wrong shape,
    or a patch mean that is not positive. ``name`` labels the image in
    messages (e.g. the sequence's first raw file).
    """
    img = np.asarray(hdr)
    if img.ndim != 2:
        raise InputError(f"patch normalisation expects a 2-D HDR mosaic, got shape {img.shape}", path=name)
    mask = np.asarray(patch_mask)
    if mask.shape != img.shape:
        raise InputError(f"white-patch mask of shape {mask.shape} does not match the HDR image {img.shape}",
                         path=name)
    if mask.dtype != bool:
        raise InputError(f"white-patch mask must be boolean, got {mask.dtype}", path=name)
    if method not in ("per_channel", "thesis"):
        raise InputError(f"patch normalisation method must be 'per_channel' or 'thesis', got {method!r}")
    if variance is not None:
        variance = np.asarray(variance)
        if variance.shape != img.shape:
            raise InputError(f"variance of shape {variance.shape} does not match the HDR image {img.shape}",
                             path=name)
    ch = channel_index(img.shape, cfa)
    groups = [(c, mask & (ch == c)) for c in range(3)] if method == "per_channel" else [(None, mask)]
    scale = np.empty(3)
    pixels = np.zeros(3, int)
    for c, sel in groups:
        label = f"channel {CHANNELS[c]}" if c is not None else "patch"
        vals = img[sel].astype(np.float64)
        if vals.size == 0:
            raise InputError(f"the white-patch mask holds no pixel{'' if c is None else ' of ' + label}", path=name)
        good = np.isfinite(vals)
        bad = 1.0 - good.mean()
        if bad > max_invalid_fraction:
            raise InputError(f"{bad:.0%} of the white patch's {label} pixels have no valid HDR value "
                             f"(saturated or unmeasured; limit {max_invalid_fraction:.0%}); the patch mean "
                             f"would be biased", path=name)
        mean = float(vals[good].mean())
        if not mean > 0:
            raise InputError(f"white-patch mean of {label} is {mean:g}, not positive; wrong mask?", path=name)
        if c is None:
            scale[:] = mean
            pixels[:] = [int(np.count_nonzero(good & (ch[sel] == k))) for k in range(3)]
        else:
            scale[c], pixels[c] = mean, int(good.sum())
    div = scale[ch]
    out = (img / div).astype(np.float32)
    var = None if variance is None else (variance / div ** 2).astype(np.float32)
    return PatchResult(image=out, variance=var, scale=scale, pixels=pixels)
