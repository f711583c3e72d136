"""Plots of an extended-Ward fit (thesis 4.5) a user would look at, and a preview render.

* :func:`plot_lobe_slices` - measured and fitted BRDF against the signed half
  angle along the fitted lobe's two principal axes (eq. 4.79-4.80: the lobe's
  x axis is where ``phi_h + lobe_rotation`` is 0 or pi, its y axis where it is
  +-pi/2);
* :func:`plot_rig_slices` - measured and fitted BRDF along the pixel column
  through the sample's centre, one panel per sample rotation, one curve per
  LED: the rig's own 1-D slices through the lobe;
* :func:`plot_residuals` - relative residuals against ``theta_h`` and
  ``phi_h`` (density plus binned median and quartiles): structure in them is
  what the model misses;
* :func:`plot_measured_vs_fitted` - density of measured against fitted values;
* :func:`render_preview` - a sphere of the fitted material rendered with
  Mitsuba 3 through the twin's ``glossrig_ward`` BSDF (imported lazily:
  ``glossrig.core`` itself knows nothing of Mitsuba, design.md).

All figures use matplotlib's Agg backend and are written as PNG.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .fit import channel_values
from .ward import WardParams, ward_from_angles

_MAX_POINTS = 60_000


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _fitted(df, p: WardParams, clip=None, clip_model=True):
    f = ward_from_angles(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"], p)
    if clip is not None and clip_model:
        f = np.minimum(f, clip)
    return f


def _measured(df, channel, clip=None):
    y = channel_values(df, channel)
    return y if clip is None else np.minimum(y, clip)


def _thin(n, rng, m=_MAX_POINTS):
    return np.arange(n) if n <= m else np.sort(rng.choice(n, m, replace=False))


def _angdist(a, b):
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def plot_lobe_slices(df, fit, path, *, channel: str | None = None, half_width_deg: float = 8.0) -> Path:
    """Measured vs fitted BRDF along the fitted lobe's principal axes (see module doc)."""
    plt = _plt()
    channel = channel or fit.channel
    p = fit.params
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, p, fit.clip, fit.clip_model)
    an = np.mod(np.asarray(df["phi_h"], float) + p.lobe_rotation, 2 * np.pi)
    th = np.rad2deg(np.asarray(df["theta_h"], float))
    hw = np.deg2rad(half_width_deg)
    xlim = float(np.clip(8 * np.rad2deg(np.arctan(p.alpha_x)), 6.0, 90.0))   # ~8 lobe widths
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, centre, name, alpha in ((axes[0], 0.0, "x (wide) axis", p.alpha_x),
                                    (axes[1], np.pi / 2, "y (narrow) axis", p.alpha_y)):
        pos, neg = _angdist(an, centre) < hw, _angdist(an, centre + np.pi) < hw
        sel = pos | neg
        x = np.where(pos, th, -th)[sel]
        ys, fs = y[sel], f[sel]
        if x.size:
            rng = np.random.default_rng(0)
            k = _thin(x.size, rng)
            ax.scatter(x[k], ys[k], s=2, c="0.35", alpha=0.35, lw=0, label="measured", rasterized=True)
            ax.scatter(x[k], fs[k], s=2, c="tab:red", alpha=0.35, lw=0, label="fitted", rasterized=True)
        else:
            ax.text(0.5, 0.5, "no samples near this axis", transform=ax.transAxes, ha="center")
        ax.set_yscale("log")
        ax.set_xlim(-xlim, xlim)
        ax.set_xlabel(r"signed $\theta_h$ (deg)")
        ax.set_title(f"lobe {name}: alpha = {alpha:.4g}  (|az - axis| < {half_width_deg:g} deg)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"BRDF, {channel} (1/sr)")
    axes[0].legend(markerscale=5, loc="upper right")
    fig.suptitle(f"{channel}: rho_d={p.rho_d:.4g} rho_s={p.rho_s:.4g} rotation={p.lobe_rotation:.3f} rad")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_rig_slices(df, fit, path, *, channel: str | None = None) -> Path:
    """Measured (dots) and fitted (lines) BRDF along the sample's central pixel
    column (around the cylinder), per sample rotation and LED."""
    plt = _plt()
    channel = channel or fit.channel
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, fit.params, fit.clip, fit.clip_model)
    u = np.asarray(df["u"])
    vals, counts = np.unique(u, return_counts=True)
    u0 = vals[np.argmax(counts)]
    col = u == u0
    rots = np.unique(np.asarray(df["rotation"], float)[col])
    leds = np.unique(np.asarray(df["led"])[col])
    n = max(1, len(rots))
    ncol = min(n, 4)
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol + 1, 3.3 * nrow), squeeze=False, sharey=True)
    cmap = plt.get_cmap("viridis")
    rot_col = np.asarray(df["rotation"], float)
    led_col = np.asarray(df["led"])
    v = np.asarray(df["v"])
    for i, rot in enumerate(rots):
        ax = axes.flat[i]
        for j, led in enumerate(leds):
            m = col & (rot_col == rot) & (led_col == led)
            if not m.any():
                continue
            o = np.argsort(v[m])
            c = cmap(j / max(1, len(leds) - 1))
            ax.plot(v[m][o], y[m][o], ".", ms=2, color=c)
            ax.plot(v[m][o], f[m][o], "-", lw=1, color=c, label=f"LED {led}")
        ax.set_yscale("log")
        ax.set_title(f"rotation {rot:g} deg, column u={u0}", fontsize=9)
        ax.set_xlabel("pixel row v (around the cylinder)")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0, 0].set_ylabel(f"BRDF, {channel} (1/sr)")
    axes[0, 0].legend(fontsize=6, ncol=2)
    fig.suptitle(f"{channel}: measured (dots) and fitted (lines)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _binned(x, r, bins):
    idx = np.digitize(x, bins) - 1
    q = np.full((3, len(bins) - 1), np.nan)
    for b in range(len(bins) - 1):
        rb = r[idx == b]
        if rb.size >= 5:
            q[:, b] = np.percentile(rb, [25, 50, 75])
    return 0.5 * (bins[1:] + bins[:-1]), q


def plot_residuals(df, fit, path, *, channel: str | None = None) -> Path:
    """Relative residuals (measured - fitted) / fitted against theta_h and phi_h."""
    plt = _plt()
    channel = channel or fit.channel
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, fit.params, fit.clip, fit.clip_model)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = (y - f) / f
    ok = np.isfinite(rel)
    th = np.rad2deg(np.asarray(df["theta_h"], float))[ok]
    ph = np.rad2deg(np.asarray(df["phi_h"], float))[ok]
    rel = rel[ok]
    lim = max(0.05, float(np.percentile(np.abs(rel), 99))) if rel.size else 1.0
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, x, name, bins in ((axes[0], th, r"$\theta_h$ (deg)", np.linspace(0, 90, 46)),
                              (axes[1], ph, r"$\phi_h$ (deg)", np.linspace(0, 360, 73))):
        if x.size:
            ax.hexbin(x, np.clip(rel, -lim, lim), gridsize=70, bins="log", cmap="Greys", mincnt=1)
            c, q = _binned(x, rel, bins)
            ax.plot(c, q[1], "r-", lw=1.2, label="median")
            ax.plot(c, q[0], "r--", lw=0.8, label="quartiles")
            ax.plot(c, q[2], "r--", lw=0.8)
        ax.axhline(0, color="tab:blue", lw=0.8)
        ax.set_ylim(-lim, lim)
        ax.set_xlabel(name)
        ax.set_ylabel("(measured - fitted) / fitted")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    st = fit.residuals
    fig.suptitle(f"{channel}: residuals  (rms relative {st.get('rms_relative', float('nan')):.3g}, "
                 f"median |rel| {st.get('median_abs_relative', float('nan')):.3g}, n={st.get('n', 0)})")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_measured_vs_fitted(df, fit, path, *, channel: str | None = None) -> Path:
    """Log-log density of measured against fitted values with the identity line."""
    plt = _plt()
    channel = channel or fit.channel
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, fit.params, fit.clip, fit.clip_model)
    ok = (y > 0) & (f > 0)
    fig, ax = plt.subplots(figsize=(5, 5))
    if ok.any():
        ax.hexbin(f[ok], y[ok], gridsize=80, bins="log", xscale="log", yscale="log", cmap="viridis", mincnt=1)
        lo, hi = float(min(f[ok].min(), y[ok].min())), float(max(f[ok].max(), y[ok].max()))
        ax.plot([lo, hi], [lo, hi], "r-", lw=0.8)
    ax.set_xlabel("fitted BRDF (1/sr)")
    ax.set_ylabel("measured BRDF (1/sr)")
    ax.set_title(f"{channel}: measured vs fitted", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_plots(df, material_fit, out_dir, *, channels=None) -> list[Path]:
    """All the plots above for each fitted channel, into ``out_dir`` (created)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("plot folder is a file", path=out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for c, fit in material_fit.fits.items():
        if channels is not None and c not in channels:
            continue
        written.append(plot_lobe_slices(df, fit, out / f"{c}_lobe_slices.png"))
        written.append(plot_rig_slices(df, fit, out / f"{c}_rig_slices.png"))
        written.append(plot_residuals(df, fit, out / f"{c}_residuals.png"))
        written.append(plot_measured_vs_fitted(df, fit, out / f"{c}_measured_vs_fitted.png"))
    return written


def preview_scene(material: dict, to_world, size: int = 160, spp: int = 64, key: float = 200.0,
                  env: float = 0.6) -> dict:
    """Mitsuba scene dict: a unit sphere of ``material`` lit by a point key light
    (intensity ``key``, W/sr) from the upper left and a uniform environment of
    radiance ``env``; camera at ``to_world``. The defaults expose a diffuse
    albedo of ~0.05 (the thesis's scratched sheets) as a visible dark grey; the
    exposure is fixed, so previews of different materials compare.)"""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {
            "type": "perspective", "fov": 30,
            "to_world": to_world,
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "gaussian"}},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": material},
        "key": {"type": "point", "position": [-3.0, 3.0, 4.0], "intensity": {"type": "rgb", "value": [key] * 3}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [env] * 3}},
    }


def render_preview(material: dict, path, *, size: int = 160, spp: int = 64, seed: int = 0) -> Path:
    """Render a sphere of the fitted material (``glossrig.core.export`` dict)
    through the twin's ``glossrig_ward`` BSDF and write an sRGB PNG.

    The sphere's tangent is Mitsuba's ``dp/du`` (around its pole axis, +y here),
    so the anisotropic highlight stretches along or across the latitude lines
    according to ``lobe_rotation``. Raises :class:`InputError` when the twin's
    BSDF (or Mitsuba) is not available."""
    try:
        from glossrig.twin.mitsuba_env import mitsuba
        mi = mitsuba()
    except ImportError as e:
        raise InputError(f"twin Ward BSDF not available ({e})") from None
    from PIL import Image

    cam = mi.ScalarTransform4f().look_at(origin=[0, 0, 5.2], target=[0, 0, 0], up=[0, 1, 0])
    scene = preview_scene(material, cam, size, spp)
    try:
        img = np.array(mi.render(mi.load_dict(scene), seed=seed), dtype=np.float64)[..., :3]
    except Exception as e:  # Mitsuba reports plugin/parameter problems as RuntimeError
        raise InputError(f"preview render failed: {e}") from None
    img = np.clip(img, 0, 1)
    srgb = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.power(img, 1 / 2.4) - 0.055)
    path = Path(path)
    Image.fromarray((srgb * 255 + 0.5).astype(np.uint8)).save(path)
    return path
