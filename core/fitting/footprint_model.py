"""The fit's footprint-averaged model: eq. 4.79 averaged over what one sample integrates.

A sample of ``glossrig extract`` is not the BRDF at one half vector: its value is the
BRDF averaged over a kernel of pixel offsets (the Bayer block's bilinear reads of the
CFA planes and each pixel's area, :func:`glossrig.core.models.footprint.luminance_kernel`),
mapped into the lobe's slope domain by the local Jacobian ``J = d(slope)/d(pixel)`` of
the half vector's slope ``tan th_h (cos phi_h, sin phi_h)``
(:mod:`glossrig.core.models.footprint`). The fit's model for such a sample is

    F_i(x) = sum_k w_k f(s_i + J_i p_k; th_in,i, th_out,i; x),

the point model ``f`` of eq. 4.79 (:func:`glossrig.core.models.ward.ward_parts`, the
project's one evaluation) at the kernel's points, the zeniths held at the sample's own;
its Jacobian is the same average of the point Jacobians
(:func:`glossrig.core.models.ward.ward_param_jacobian`), so the covariance and the
uncertainty budget describe the footprint-averaged model.

**How J is obtained.** From the samples table itself: the extracted half-vector slopes
of neighbouring Bayer blocks (2 px apart) of the same LED and sample rotation, by
central differences (one-sided at a border), :func:`glossrig.core.models.footprint.slope_jacobian`.
The table's angles come from the calibrated geometry (camera intrinsics, holder and
cylinder poses, lamp positions), so J is the calibrated one, and nothing else need be
stored. It needs the columns ``u, v, led, rotation`` with the rows on the 2-px grid of
Bayer blocks that ``glossrig extract`` writes (u, v even); a table without them (e.g. point
values at every pixel of :func:`glossrig.core.extraction.cylinder.nominal_samples`) keeps
the point model, and so does a row without a neighbouring block along either axis (the
fit records how many rows have a footprint, ``footprint.rows_with_jacobian``).

**The kernel.** Per channel: luminance is Rec. 709 Y of the four CFA planes' bilinear
reads, r, g, b their own planes (16 lattice points for luminance, 8 for g, 4 for r and
b); each pixel's area by Gauss-Legendre quadrature per pixel axis, of an order chosen
from how far one pixel moves the slope relative to the lobe's narrower width,
``h / alpha_min`` with ``h`` the 90th percentile of ``|J e_axis|`` over the rows near
the lobe (:func:`kernel_orders`): 1 point where ``h / alpha_min < 0.02`` (the pixel's own
extent is invisible: the box's variance h^2 / 12 is left out), 2 below 0.5 (exact for
integrands cubic across a pixel, and the box's variance exactly), else
``ceil(2 + h / alpha_min)`` up to 8. Measured on a scale-0.25 twin table (one pixel
column moves the slope ~0.0004, one row ~0.0055) against a 12 x 12-point rule, largest
relative difference over the samples: 1.7e-5 for alpha 0.034 (1 x 2 points, sample_2_6),
2e-5 for alpha 0.0075 (2 x 3), 2.2e-4 for alpha 0.0031 (2 x 4, transparency_sheet);
with 1 point along the columns at alpha 0.0075 it was 1.6e-3. The fit chooses
the orders from its start and, where the optimum's lobe needs finer ones, polishes
again with them. The Bayer pattern is the rig's (``cfa``, default RGGB, the thesis's
D750 and the twin's sensor).

**Where it is evaluated.** Only rows where some kernel point can reach the lobe:
``sqrt(q_i) - reach_i / min(alpha) < sqrt(Q_ACTIVE)`` (``q_i`` the point exponent,
``reach_i = |J_i|_2 max_k |p_k| >= max_k |J_i p_k|`` a bound on how far the kernel moves the slope, so the
left side bounds ``sqrt(q)`` at every kernel point from below). Elsewhere every kernel
point's lobe is below ``exp(-Q_ACTIVE) ~ 2e-9`` of its peak and the point value is used.

**Not modelled** (the uncertainty budget's ``footprint`` component,
:mod:`glossrig.core.fitting.uncertainty`): the LED's finite emitting aperture (the twin's
LED is a point; the real rig's is a 0.75 mm channel 300 mm away), and the change of
``1 / sqrt(cos th_i cos th_o)`` across the footprint (relative ~1e-4 over 0.3 deg).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from glossrig.core.models.ward import WardGeometry, ward_param_jacobian, ward_parts

#: Kernel points are evaluated where the lower bound of the exponent over the kernel
#: is below this (exp(-20) ~ 2e-9 of the lobe's peak).
Q_ACTIVE = 20.0
#: Rows per evaluation chunk (times the kernel's points: the working arrays' length).
CHUNK_POINTS = 1 << 20
#: The R, G, B weights of each channel's value (luminance: Rec. 709 Y).
CHANNEL_RGB = {"r": (1.0, 0.0, 0.0), "g": (0.0, 1.0, 0.0), "b": (0.0, 0.0, 1.0)}
FOOTPRINT_COLUMNS = ("u", "v", "led", "rotation")


def kernel_orders(J: np.ndarray, has: np.ndarray, alpha_min: float) -> tuple[int, int]:
    """Gauss-Legendre orders (along pixel columns, along rows) of the pixel's area for a
    lobe of narrower width ``alpha_min`` (module docstring), from the rows ``has``."""
    orders = []
    for axis in range(2):
        col = np.hypot(J[has, 0, axis], J[has, 1, axis])
        r = float(np.percentile(col, 90)) / max(alpha_min, 1e-12) if col.size else 0.0
        orders.append(1 if r < 0.02 else 2 if r < 0.5 else int(min(8, math.ceil(2 + r))))
    return orders[0], orders[1]


def channel_kernel(channel: str, cfa="RGGB", orders: tuple[int, int] = (2, 2)) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets ``(k, 2)`` and weights ``(k,)`` of one channel's sample value
    (module docstring; luminance, and any name not r, g, b, is Rec. 709 Y), the pixel's
    area by Gauss-Legendre of ``orders`` (columns, rows)."""
    from glossrig.core.models.footprint import luminance_kernel

    return luminance_kernel(cfa, "area", weights=CHANNEL_RGB.get(channel),
                            pixel_rule=f"gauss{int(orders[0])}x{int(orders[1])}")


@dataclass
class SampleFootprint:
    """Per-sample footprint of the fit's rows: ``J`` ``(n, 2, 2)`` slope per pixel
    (rows without one: ``has`` False, J 0), ``smax`` its largest singular value, and
    the kernel of ``channel`` (``offs (k, 2)``, ``w (k,)``, pixel-area ``orders``)."""

    J: np.ndarray
    has: np.ndarray
    smax: np.ndarray
    channel: str = "luminance"
    cfa: str = "RGGB"
    orders: tuple[int, int] = (2, 2)
    offs: np.ndarray = field(default_factory=lambda: np.zeros((1, 2)))
    w: np.ndarray = field(default_factory=lambda: np.ones(1))

    def __post_init__(self):
        self.offs, self.w = channel_kernel(self.channel, self.cfa, self.orders)

    def take(self, idx) -> SampleFootprint:
        return SampleFootprint(self.J[idx], self.has[idx], self.smax[idx], self.channel, self.cfa, self.orders)

    def with_orders(self, orders) -> SampleFootprint:
        return SampleFootprint(self.J, self.has, self.smax, self.channel, self.cfa, tuple(orders))

    def for_channel(self, channel: str) -> SampleFootprint:
        return SampleFootprint(self.J, self.has, self.smax, channel, self.cfa, self.orders)

    def orders_for(self, geo: WardGeometry, x, *, log_alpha: bool = False) -> tuple[int, int]:
        """The pixel quadrature the lobe ``x`` needs (:func:`kernel_orders`), from the
        rows whose kernel can reach it (all rows with a Jacobian where none can)."""
        _, parts = ward_parts(geo, x, log_alpha=log_alpha)
        near = np.zeros(len(self), bool)
        near[active_rows(geo, self, x, parts, log_alpha=log_alpha)] = True
        ax, ay = _alphas(x, log_alpha)
        return kernel_orders(self.J, near if near.any() else self.has, min(ax, ay))

    @property
    def reach(self) -> np.ndarray:
        """``|J|_2 max_k |p_k| >= max_k |J p_k|``: how far the kernel can move the slope."""
        return self.smax * float(np.max(np.hypot(self.offs[:, 0], self.offs[:, 1])))

    def __len__(self) -> int:
        return int(self.has.size)

    @property
    def n_with_jacobian(self) -> int:
        return int(self.has.sum())

    def describe(self) -> dict:
        """What fit.json records of the footprint model."""
        return {"model": "footprint-averaged", "jacobian": "from neighbouring blocks of the samples table",
                "rows": len(self), "rows_with_jacobian": self.n_with_jacobian, "cfa": self.cfa,
                "pixel_quadrature": list(self.orders), "kernel_points": int(self.w.size)}


def sample_footprint(J, channel: str = "luminance", cfa="RGGB", orders=(2, 2)) -> SampleFootprint:
    """A :class:`SampleFootprint` from per-row Jacobians (NaN rows: no footprint)."""
    J = np.array(J, dtype=float).reshape(-1, 2, 2)
    has = np.all(np.isfinite(J.reshape(len(J), 4)), axis=1)
    J[~has] = 0.0
    smax = np.linalg.norm(J, ord=2, axis=(1, 2)) if len(J) else np.zeros(0)
    return SampleFootprint(J, has, smax, channel, cfa, tuple(orders))


def table_jacobian(df) -> np.ndarray | None:
    """Per-row ``d(slope)/d(pixel)`` of a samples table from its neighbouring blocks
    (:func:`glossrig.core.models.footprint.slope_jacobian`), or None when the table lacks
    ``u, v, led, rotation`` or its rows are not on the grid of 2x2 Bayer blocks that
    ``glossrig extract`` writes (u and v even): the block values are what the kernel
    describes, and the neighbouring blocks 2 px apart are what the estimate needs."""
    from glossrig.core.models.footprint import slope_jacobian

    if any(c not in df for c in FOOTPRINT_COLUMNS):
        return None
    u, v = np.asarray(df["u"]), np.asarray(df["v"])
    if u.size == 0 or np.any(u % 2) or np.any(v % 2):
        return None
    return slope_jacobian(df)


def _alphas(x, log_alpha: bool) -> tuple[float, float]:
    a, b = float(x[2]), float(x[3])
    return (math.exp(a), math.exp(b)) if log_alpha else (a, b)


def active_rows(geo: WardGeometry, fp: SampleFootprint, x, parts, *, log_alpha: bool = False) -> np.ndarray:
    """Indices of the rows whose kernel can reach the lobe (module docstring)."""
    ax, ay = _alphas(x, log_alpha)
    u, v, _ = parts
    q = (u / ax) ** 2 + (v / ay) ** 2
    lb = np.sqrt(q) - fp.reach / min(ax, ay)
    return np.flatnonzero(fp.has & (lb < math.sqrt(Q_ACTIVE)))


def _kernel_geometry(geo: WardGeometry, fp: SampleFootprint, i: np.ndarray) -> WardGeometry:
    ox, oy = fp.offs[:, 0], fp.offs[:, 1]
    J = fp.J[i]
    k = ox.size
    sx = geo.sx[i, None] + J[:, 0, 0, None] * ox + J[:, 0, 1, None] * oy
    sy = geo.sy[i, None] + J[:, 1, 0, None] * ox + J[:, 1, 1, None] * oy
    g = np.repeat(geo.g[i], k)
    kd = geo.kd if not isinstance(geo.kd, np.ndarray) else np.repeat(geo.kd[i], k)
    return WardGeometry(sx.ravel(), sy.ravel(), g, kd, (i.size * k,))


def footprint_eval(geo: WardGeometry, fp: SampleFootprint, x, *, jac: bool = False, log_alpha: bool = False):
    """The footprint-averaged eq. 4.79 at ``x`` for every row (module docstring) and,
    with ``jac``, its Fortran-ordered ``(n, 5)`` Jacobian (the kernel average of
    :func:`glossrig.core.models.ward.ward_param_jacobian`; with ``log_alpha`` by
    ``ln alpha``). Returns ``f`` or ``(f, J)``; rows without a footprint, and rows the
    kernel cannot bring near the lobe, carry the point model."""
    f, parts = ward_parts(geo, x, log_alpha=log_alpha)
    Jac = ward_param_jacobian(geo, x, parts, log_alpha=log_alpha) if jac else None
    idx = active_rows(geo, fp, x, parts, log_alpha=log_alpha)
    k = fp.w.size
    step = max(1, CHUNK_POINTS // max(k, 1))
    for a in range(0, idx.size, step):
        i = idx[a:a + step]
        sub = _kernel_geometry(geo, fp, i)
        fk, pk = ward_parts(sub, x, log_alpha=log_alpha)
        f[i] = fk.reshape(i.size, k) @ fp.w
        if jac:
            Jk = ward_param_jacobian(sub, x, pk, log_alpha=log_alpha)
            assert Jac is not None
            Jac[i] = np.einsum("mkp,k->mp", Jk.reshape(i.size, k, 5), fp.w)
    return (f, Jac) if jac else f
