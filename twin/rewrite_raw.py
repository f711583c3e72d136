"""Hide sensor effects in an existing capture by rewriting its raw values, outside the renderer.

It lives in the twin because it writes DNGs (:mod:`glossrig.twin.dng`); ``core``
imports neither the twin nor the hardware layer (tests/test_layering.py).

Used by the tests and the blind study so that finding these effects does not
lean on the twin's own implementation: each DNG of the capture is decoded with
:func:`glossrig.core.calibration.raw.read_raw`, its mosaic changed, and written back with
:func:`glossrig.twin.dng.write_dng` (same CFA, levels, exposure metadata); the
manifest's checksums are updated. The stated black level is left unchanged.

* ``black_level_offset=b``: every DN + b (the sensor's true black differs by b).
* ``sensor_nonlinearity=c``: x -> x (1 - c x / (white - black)) for the signal x above black
  (negative read noise left as it is; saturated pixels stay saturated).
* ``axis_step=s``: the signal above black times 1 + s in the right half of the image (x at or
  beyond the middle; on the thesis rig the cylinder axis runs along the image's x axis, so this
  is a step half-way along the axis: a smudge or crease of the wrapped sample). No cause of
  diagnose's catalogue models it: diagnose must call it "unexplained", along the axis (issue 14).
* ``exposure_step=s``: the signal above black times 1 + s in every frame of a nominal exposure of
  1 s or longer, every LED alike (a camera that reads long exposures another way: long-exposure
  noise reduction, another readout mode). Outside the catalogue too - neither an LED's drift nor a
  shutter error (:mod:`glossrig.core.diagnose.frame_gains`): "unexplained", along exposure_s.
* ``vignetting=k``: the signal above black times ``1 - k r^2 / r_corner^2``, r from the image's
  centre (the lens's optical centre is not in the raw file; the rig's cameras have it at the centre
  to within a few pixels) - as the twin's lens fall-off (:mod:`glossrig.twin.effects`), applied to the
  whole frame: the sample, the holder and the marker's white patch alike (saturated pixels stay
  saturated).

**Rounding.** A raw file holds integers, and the rewritten value ``y`` is generally not one. Rounding
it to the nearest integer is a deterministic map that loses a small change of a dark pixel: a shutter
error of 8 % of the frame's time turns x DN above black into round(1.08 x) = x for every x up to 6
DN, so the effect is simply not in the darkest pixels of the shortest frames - where a shutter error
is largest. Measured on a matte twin capture's sample crop (two LEDs, a shutter error of 2e-5 s on
a shortest exposure of 2.5e-4 s, the same noise with and without it): the frame gains read 83 % of
it, 2.4 of their standard errors low. So the value is rounded stochastically - ``floor(y + u)``, u uniform in [0, 1) - whose
expectation is y: the written effect is the intended one on average at every signal level, at the
price of a rounding noise of at most 1/4 DN^2 (the camera's own quantisation is 1/12). An integer y
(a whole-DN black offset, a pixel the effect leaves alone) is written unchanged. The draws are
seeded by the effect, its value and the file's name, so a rewrite is reproducible.
"""
from __future__ import annotations

import shutil
import zlib
from datetime import datetime
from pathlib import Path

import numpy as np

from glossrig.core.capture import load_manifest
from glossrig.core.errors import InputError

REWRITABLE = ("black_level_offset", "sensor_nonlinearity", "axis_step", "shutter_error", "channel_response",
              "vignetting", "exposure_step")
#: exposure_step acts on the frames of at least this nominal exposure (s)
LONG_EXPOSURE_S = 1.0
CFA_NAMES = {0: "R", 1: "G", 2: "B"}


def stochastic_round(y: np.ndarray, key: str) -> np.ndarray:
    """``floor(y + u)`` with u uniform in [0, 1), seeded by ``key``: integers whose expectation is
    ``y`` (module docstring, "Rounding"); an integer value is returned unchanged."""
    u = np.random.default_rng(zlib.crc32(key.encode())).random(np.shape(y))
    return np.floor(np.asarray(y, float) + u)


def rewrite_capture(src, dst, effect: str, value: float) -> Path:
    from .dng import write_dng

    if effect not in REWRITABLE:
        raise InputError(f"can only rewrite {', '.join(REWRITABLE)}, not {effect!r}")
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise InputError("destination exists", path=dst)
    shutil.copytree(src, dst)
    man = load_manifest(dst)
    for im in man.select("sequence"):
        p = dst / im.file
        fr = man.read_raw(im)
        dn = fr.mosaic.astype(np.float64)
        black = np.tile(np.asarray(fr.black, float).reshape(2, 2), (dn.shape[0] // 2 + 1, dn.shape[1] // 2 + 1))
        black = black[:dn.shape[0], :dn.shape[1]]
        if effect == "black_level_offset":
            dn = dn + value
        elif effect == "axis_step":
            x = fr.origin[0] + np.arange(dn.shape[1])[None, :]
            step = np.where(x >= fr.full_size[0] // 2, 1.0 + value, 1.0)
            dn = np.where(dn >= fr.white, dn, black + (dn - black) * step)
        elif effect == "vignetting":
            w, h = fr.full_size
            cx, cy = (w - 1) / 2, (h - 1) / 2
            x = fr.origin[0] + np.arange(dn.shape[1])[None, :] - cx
            y = fr.origin[1] + np.arange(dn.shape[0])[:, None] - cy
            fall = 1.0 - value * (x ** 2 + y ** 2) / (cx ** 2 + cy ** 2)
            dn = np.where(dn >= fr.white, dn, black + (dn - black) * fall)
        elif effect == "exposure_step":
            if im.exposure_s >= LONG_EXPOSURE_S:
                dn = np.where(dn >= fr.white, dn, black + (dn - black) * (1.0 + value))
        elif effect == "shutter_error":
            x = dn - black
            dn = np.where(dn >= fr.white, dn, black + x * (im.exposure_s + value) / im.exposure_s)
        else:
            # sensor_nonlinearity on every pixel, channel_response on the red ones. The signal above
            # black, read noise included: compressing max(x, 0) instead would move every dark pixel's
            # negative noise to 0, a +1.1 DN offset (measured) that then reads as a black level offset
            x = dn - black
            keep = dn >= fr.white
            if effect == "channel_response":
                keep = keep | (fr.channel_index() != 0)
            dn = np.where(keep, dn, black + x * (1.0 - value * np.maximum(x, 0) / (fr.white - black)))
        mosaic = np.clip(stochastic_round(dn, f"{effect}={value!r}:{im.file}"), 0, fr.white).astype(np.uint16)
        cfa = "".join(CFA_NAMES[int(c)] for c in np.asarray(fr.cfa).ravel())
        im.sha256 = write_dng(p, mosaic, cfa=cfa, black_level=tuple(int(b) for b in np.asarray(fr.black).ravel()),
                              white_level=int(fr.white), exposure_s=im.exposure_s, iso=im.iso,
                              aperture=im.aperture, time=datetime.fromisoformat(im.time), overwrite=True)
    man.meta.setdefault("hidden_outside_twin", {})[effect] = value
    man.save()
    return dst
