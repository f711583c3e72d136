"""Helpers shared by several test modules, imported normally (``from helpers import ...``;
tests/ is on sys.path as the folder of the test modules and conftest.py). Test modules
never import one another: what two of them need lives here or in conftest.py."""
from __future__ import annotations

import functools
import io
from pathlib import Path

import numpy as np

# ------------------------------------------------------------------ figures


def assert_image_has_content(path, *, size: tuple[int, int] | None = None, aspect: float | None = None,
                             min_size: tuple[int, int] = (16, 16), min_std: float = 0.01, rel: float = 0.02) -> np.ndarray:
    """Fail unless ``path`` (a file, or the image file's bytes) is a readable image that is
    not blank: the standard deviation of its pixel values, on a 0..1 scale (8-bit /255,
    16-bit /65535; others by their own range), exceeds ``min_std``. ``size`` is the exact
    ``(width, height)`` in pixels, ``aspect`` width/height within relative ``rel`` (for a
    matplotlib figure: figsize[0] / figsize[1]), ``min_size`` the least width and height.
    Returns the pixels as float (0..1 for integer images), for checks of their own."""
    from PIL import Image

    if isinstance(path, (bytes, bytearray)):
        src, path = io.BytesIO(path), "<image bytes>"
    else:
        path = src = Path(path)
        assert path.is_file(), f"{path}: not written"
    try:
        with Image.open(src) as im:
            im.load()
            w, h = im.size
            if im.mode in ("I;16", "I;16B", "I;16L", "I;16N"):
                a = np.asarray(im, dtype=float) / 65535.0
            elif im.mode in ("I", "F"):
                a = np.asarray(im, dtype=float)
                span = float(np.nanmax(a) - np.nanmin(a)) if a.size else 0.0
                a = (a - np.nanmin(a)) / span if span > 0 else np.zeros_like(a)
            else:
                a = np.asarray(im.convert("RGBA" if "A" in im.getbands() else "RGB"), dtype=float) / 255.0
    except OSError as e:
        raise AssertionError(f"{path}: not a readable image ({e})") from e
    assert w >= min_size[0] and h >= min_size[1], f"{path}: {w} x {h} px, smaller than {min_size[0]} x {min_size[1]}"
    if size is not None:
        assert (w, h) == tuple(size), f"{path}: {w} x {h} px, expected {size[0]} x {size[1]}"
    if aspect is not None:
        assert abs(w / h / aspect - 1) <= rel, f"{path}: aspect {w / h:.3f} (w/h), expected {aspect:.3f}"
    std = float(np.nanstd(a))
    assert std > min_std, f"{path}: blank or constant image (pixel std {std:.4f} <= {min_std})"
    return a


# ------------------------------------------------------------------ Ward fits on nominal rig angles
# (tests/test_fit.py and tests/test_fit_recovery.py)

ROTATIONS = (-45, 0, 45, 90)


@functools.cache
def geometry(scale: float = 0.05, leds: str = "middle", rotations=ROTATIONS):
    """The angles the thesis rig measures (core.cylinder.nominal_samples) at ``scale``:
    ``leds`` of the default rig, sample ``rotations`` in degrees (thesis 6.2)."""
    from glossrig.core.extraction.cylinder import nominal_samples
    from glossrig.core.rig import default_rig_path, load_rig

    rig = load_rig(default_rig_path())
    return nominal_samples(rig, rig.select_leds(leds), list(rotations), scale)


def material(name: str):
    """Table 9.1 materials (thesis) and the repository's isotropic test material, as WardParams."""
    from glossrig.core.models.materials import parse_material

    return parse_material(name).ward


def noisy(geo, p, noise=0.03, seed=1):
    """The Ward BRDF ``p`` at the angles of ``geo`` with multiplicative Gaussian noise."""
    from glossrig.core.models.ward import ward_from_angles

    f = ward_from_angles(geo["theta_in"], geo["theta_out"], geo["theta_h"], geo["phi_h"], p)
    return f * (1 + noise * np.random.default_rng(seed).standard_normal(f.size))
