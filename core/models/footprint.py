"""The angular footprint of one BRDF sample: what an area-integrating pixel averages.

Each BRDF sample of ``glossrig extract`` is one 2x2 Bayer block: its R, G, B values are
read at the block centre by bilinear interpolation from the four CFA planes
(:func:`glossrig.core.extraction.extract.block_values`), and each CFA pixel integrates the image
over its area. The value a sample carries is therefore the BRDF averaged over a kernel
of pixel offsets ``p`` (:func:`luminance_kernel`, a few pixels wide), mapped into the
lobe's domain by the local Jacobian ``J = d(slope)/d(pixel)`` (:func:`slope_jacobian`) of
the half vector's slope ``tan(theta_h) (cos phi_h, sin phi_h)``, the variable of Ward's
exponent (thesis eq. 4.79). Where the lobe is not much wider than ``|J| p`` the sample is
not the point value: the average lowers the peak (by ~sigma^2 / alpha^2 for a kernel of
variance sigma^2 in slope) and raises the tails, a bias that grows with theta_h's
distance from the specular peak. :func:`footprint_average` is that forward model; the
pipeline's ground-truth comparisons (validation/pipeline_study.py,
validation/recovery_footprint.py) use it to tell the pixel's physics from pipeline error.
"""
from __future__ import annotations

import math

import numpy as np

def _box(step: float = 0.25) -> dict:
    """1-D pixel-area (box) kernel on a grid of ``step`` px: midpoint rule."""
    n = int(round(1 / step))
    return {round((i + 0.5) * step - 0.5, 6): 1.0 / n for i in range(n)}


def _conv(a: dict, b: dict) -> dict:
    out: dict = {}
    for x, w in a.items():
        for y, v in b.items():
            k = round(x + y, 6)
            out[k] = out.get(k, 0.0) + w * v
    return out


def luminance_kernel(cfa="RGGB", render: str = "area", *, weights=None,
                     pixel_rule: str = "midpoint") -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets ``(m, 2)`` (column, row) from the block centre and weights ``(m,)``
    of the luminance value of one sample (``weights``: the R, G, B weights of another
    channel instead of Rec. 709 Y, e.g. ``(1, 0, 0)`` for r).

    Per CFA plane (di, dj), :func:`glossrig.core.extraction.extract.block_values` reads the plane
    bilinearly at the block centre, which is (0.5 - di, 0.5 - dj) px from the plane's
    pixel (di, dj) of the block: along rows, weight 3/4 at -0.5 px and 1/4 at +1.5 px
    for di = 0, 1/4 at -1.5 and 3/4 at +0.5 for di = 1 (columns alike). G is the mean
    of its two planes, luminance is Rec. 709 Y of R, G, B. Each pixel integrates its
    area (box); ``render="old"`` adds a 1-px tent (bilinear read of a canvas at the
    output resolution, averaged over the sub-pixel phase). The pixel's area is
    integrated by the midpoint rule on a 1/4-px grid (``pixel_rule="midpoint"``) or by
    N-point Gauss-Legendre per axis (``"gaussN"``: N^2 points a pixel, exact for
    integrands of degree 2N - 1 across the pixel; ``"gauss2"`` already gives the box's
    variance 1/12 px^2 exactly; ``"gaussNxM"``: N along columns, M along rows)."""
    from glossrig.core.calibration.demosaic import cfa_array
    from glossrig.core.samples import LUMINANCE_WEIGHTS

    cid = cfa_array(cfa)
    n_planes = np.bincount(cid.ravel(), minlength=3)
    chan_w = LUMINANCE_WEIGHTS if weights is None else tuple(float(x) for x in weights)
    lattice = {0: {-0.5: 0.75, 1.5: 0.25}, 1: {-1.5: 0.25, 0.5: 0.75}}
    orders = pixel_rule[5:].split("x") if pixel_rule.startswith("gauss") else []
    if orders and len(orders) <= 2 and all(o.isdigit() and int(o) >= 1 for o in orders):
        def gauss(m):
            nodes, gw = np.polynomial.legendre.leggauss(m)
            return {round(0.5 * float(x), 9): 0.5 * float(g) for x, g in zip(nodes, gw)}

        pix_c, pix_r = gauss(int(orders[0])), gauss(int(orders[-1]))
    elif pixel_rule == "midpoint":
        pix_c = pix_r = _box()
    else:
        raise ValueError(f"pixel_rule must be 'midpoint', 'gaussN' or 'gaussNxM' (N, M >= 1), got {pixel_rule!r}")
    if render == "old":
        pix_c, pix_r = (_conv(p, _conv(_box(), _box())) for p in (pix_c, pix_r))
    elif render != "area":
        raise ValueError(f"render must be 'area' or 'old', got {render!r}")
    acc: dict = {}
    for di in range(2):
        for dj in range(2):
            c = int(cid[di, dj])
            w_c = chan_w[c] / n_planes[c]
            rows, cols = _conv(lattice[di], pix_r), _conv(lattice[dj], pix_c)
            for y, wy in rows.items():
                for x, wx in cols.items():
                    acc[(x, y)] = acc.get((x, y), 0.0) + w_c * wy * wx
    acc = {k: v for k, v in acc.items() if v != 0.0}       # planes of channels with weight 0
    offs = np.array(list(acc.keys()), float)
    w = np.array(list(acc.values()))
    return offs, w / w.sum()


def slopes(theta_h, phi_h) -> np.ndarray:
    t = np.tan(np.asarray(theta_h, float))
    return np.stack([t * np.cos(phi_h), t * np.sin(phi_h)], axis=-1)


def exponent(s: np.ndarray, p) -> np.ndarray:
    """Ward's exponent tan^2 th_h (cos^2 a_n / ax^2 + sin^2 a_n / ay^2), a_n = phi_h + rot
    (eq. 4.79-4.80), from the slopes ``s``: the lobe is exp(-q), half maximum at q = ln 2."""
    c, sn = math.cos(p.lobe_rotation), math.sin(p.lobe_rotation)
    sx, sy = c * s[:, 0] - sn * s[:, 1], sn * s[:, 0] + c * s[:, 1]
    return (sx / p.alpha_x) ** 2 + (sy / p.alpha_y) ** 2


def slope_jacobian(df) -> np.ndarray:
    """``(n, 2, 2)`` d(slope)/d(u, v) per pixel, from neighbouring blocks (2 px apart) of
    the same LED and rotation (central differences, one-sided at the border; NaN where
    a block has no neighbour along an axis)."""
    s = slopes(df["theta_h"].to_numpy(), df["phi_h"].to_numpy())
    J = np.full((len(df), 2, 2), np.nan)
    u = df["u"].to_numpy() // 2
    v = df["v"].to_numpy() // 2
    for _, idx in df.groupby(["led", "rotation"]).indices.items():
        uu, vv = u[idx] - u[idx].min(), v[idx] - v[idx].min()
        grid = np.full((vv.max() + 1, uu.max() + 1), -1, np.int64)
        grid[vv, uu] = idx
        for axis, (du, dv) in enumerate(((1, 0), (0, 1))):
            def at(a, b, grid=grid, idx=idx):
                ok = (a >= 0) & (b >= 0) & (a < grid.shape[1]) & (b < grid.shape[0])
                out = np.full(idx.size, -1, np.int64)
                out[ok] = grid[b[ok], a[ok]]
                return out
            fwd, bwd = at(uu + du, vv + dv), at(uu - du, vv - dv)
            hi = np.where(fwd >= 0, fwd, idx)
            lo = np.where(bwd >= 0, bwd, idx)
            span = 2.0 * ((fwd >= 0).astype(float) + (bwd >= 0))
            with np.errstate(invalid="ignore", divide="ignore"):
                J[idx, :, axis] = (s[hi] - s[lo]) / span[:, None]
    return J


def footprint_average(df, p, J, offs, w, q_max: float = 400.0, chunk: int = 4000) -> np.ndarray:
    """The BRDF of ``p`` (eq. 4.79, :func:`glossrig.core.models.ward.ward_from_angles`) averaged
    over each sample's kernel ``sum_k w_k f(s + J p_k)``, in- and outgoing zeniths held
    at the sample's own. Samples whose point exponent exceeds ``q_max`` and samples
    without a Jacobian keep the point value."""
    from glossrig.core.models.ward import ward_from_angles

    ti, to = df["theta_in"].to_numpy(), df["theta_out"].to_numpy()
    th, ph = df["theta_h"].to_numpy(), df["phi_h"].to_numpy()
    f = ward_from_angles(ti, to, th, ph, p)
    s = slopes(th, ph)
    q = exponent(s, p)
    todo = np.flatnonzero((q < q_max) & np.all(np.isfinite(J.reshape(len(df), 4)), axis=1))
    out = f.copy()
    for a in range(0, todo.size, chunk):
        i = todo[a:a + chunk]
        sk = s[i, None, :] + np.einsum("nij,kj->nki", J[i], offs)          # (n, k, 2)
        thk = np.arctan(np.hypot(sk[..., 0], sk[..., 1]))
        phk = np.arctan2(sk[..., 1], sk[..., 0])
        fk = ward_from_angles(ti[i, None], to[i, None], thk, phk, p)
        out[i] = fk @ w
    return out


def kernel_rms_px(offs, w, direction) -> float:
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    x = offs @ d
    m = np.sum(w * x)
    return float(np.sqrt(np.sum(w * (x - m) ** 2)))


def footprint_truth(df, p, cfa: str = "RGGB") -> np.ndarray:
    """The luminance BRDF of Ward parameters ``p`` that each sample of the table ``df``
    should carry if extraction is exact: the point value averaged over the sample's
    pixel footprint (area-integrating pixels, the Bayer block's bilinear reads), with the
    Jacobian from the table's own neighbouring blocks."""
    offs, w = luminance_kernel(cfa)
    return footprint_average(df, p, slope_jacobian(df), offs, w)
