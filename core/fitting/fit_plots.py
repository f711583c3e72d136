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
* :func:`plot_uncertainty_budget` - the GUM budget of every channel
  (:mod:`glossrig.core.fitting.uncertainty`) as a table per channel, with each
  component's share of the combined variance as bars;
The preview sphere of the fitted material (``render_preview``) is rendered with
Mitsuba 3 and lives in :mod:`glossrig.twin.material_renders` (same name and
arguments): ``glossrig.core`` imports neither Mitsuba nor the twin (design.md).

All figures use matplotlib's Agg backend, constrained layout (no overlapping
labels) and are written as PNG.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fitting.fit import channel_values
from glossrig.core.models.ward import WardParams, ward_from_angles

_MAX_POINTS = 60_000
_DPI = 120


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _ticks(n):
    from matplotlib.ticker import MaxNLocator as _M

    return _M(n)


def _log_ticks(axis):
    """Labels at 1, 2 and 5 times the powers of ten and no labelled minor ticks: on a
    log axis spanning about a decade matplotlib labels the minor ticks too, and on a
    horizontal axis their labels (``2x10^-2 3x10^-2 ...``) run into each other."""
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(LogFormatterSciNotation(labelOnlyBase=False))
    axis.set_minor_formatter(NullFormatter())


_LAST_J: list = [None, None]


def _fitted(df, p: WardParams, clip=None, clip_model=True, footprint: dict | None = None, channel="luminance"):
    """The fitted model at the table's samples: the footprint average where the fit used
    it (``footprint``: the fit's ``footprint`` record), else the point model."""
    f = None
    if footprint and footprint.get("model") == "footprint-averaged":
        from glossrig.core.fitting.footprint_model import footprint_eval, sample_footprint, table_jacobian
        from glossrig.core.models.ward import ward_geometry

        if _LAST_J[0] is not df:            # one table's Jacobian serves every plot of every channel
            _LAST_J[:] = [df, table_jacobian(df)]
        J = _LAST_J[1]
        if J is not None and len(J) == len(df):
            fp = sample_footprint(J, channel, footprint.get("cfa", "RGGB"),
                                  tuple(footprint.get("pixel_quadrature", (2, 2))))
            geo = ward_geometry(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"])
            f = footprint_eval(geo, fp, [p.rho_d, p.rho_s, p.alpha_x, p.alpha_y, p.lobe_rotation])
    if f is None:
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
    f = _fitted(df, p, fit.clip, fit.clip_model, fit.footprint, channel)
    an = np.mod(np.asarray(df["phi_h"], float) + p.lobe_rotation, 2 * np.pi)
    th = np.rad2deg(np.asarray(df["theta_h"], float))
    hw = np.deg2rad(half_width_deg)
    xlim = float(np.clip(8 * np.rad2deg(np.arctan(p.alpha_x)), 6.0, 90.0))   # ~8 lobe widths
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True, layout="constrained")
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
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_rig_slices(df, fit, path, *, channel: str | None = None) -> Path:
    """Measured (dots) and fitted (lines) BRDF along the sample's central pixel
    column (around the cylinder), per sample rotation and LED."""
    plt = _plt()
    channel = channel or fit.channel
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, fit.params, fit.clip, fit.clip_model, fit.footprint, channel)
    u = np.asarray(df["u"])
    vals, counts = np.unique(u, return_counts=True)
    u0 = vals[np.argmax(counts)]
    col = u == u0
    rots = np.unique(np.asarray(df["rotation"], float)[col])
    leds = np.unique(np.asarray(df["led"])[col])
    n = max(1, len(rots))
    ncol = min(n, 4)
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.4 * ncol + 1, 3.8 * nrow + 0.5), squeeze=False, sharey=True,
                             layout="constrained")
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
        ax.xaxis.set_major_locator(_ticks(5))
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0, 0].set_ylabel(f"BRDF, {channel} (1/sr)")
    axes[0, 0].legend(fontsize=6, ncol=2)
    fig.suptitle(f"{channel}: measured (dots) and fitted (lines)")
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
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
    f = _fitted(df, fit.params, fit.clip, fit.clip_model, fit.footprint, channel)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = (y - f) / f
    ok = np.isfinite(rel)
    th = np.rad2deg(np.asarray(df["theta_h"], float))[ok]
    ph = np.rad2deg(np.asarray(df["phi_h"], float))[ok]
    rel = rel[ok]
    lim = max(0.05, float(np.percentile(np.abs(rel), 99))) if rel.size else 1.0
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), layout="constrained")
    for ax, x, name, bins in ((axes[0], th, r"$\theta_h$ (deg)", np.linspace(0, 90, 46)),
                              (axes[1], ph, r"$\phi_h$ (deg)", np.linspace(0, 360, 73))):
        ax.xaxis.set_major_locator(_ticks(7))
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
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_measured_vs_fitted(df, fit, path, *, channel: str | None = None) -> Path:
    """Log-log density of measured against fitted values with the identity line."""
    plt = _plt()
    channel = channel or fit.channel
    y = _measured(df, channel, fit.clip)
    f = _fitted(df, fit.params, fit.clip, fit.clip_model, fit.footprint, channel)
    ok = (y > 0) & (f > 0)
    fig, ax = plt.subplots(figsize=(6.6, 5.8), layout="constrained")
    if ok.any():
        hb = ax.hexbin(f[ok], y[ok], gridsize=80, bins="log", xscale="log", yscale="log", cmap="viridis", mincnt=1)
        fig.colorbar(hb, ax=ax, label="samples per hexagon")
        lo, hi = float(min(f[ok].min(), y[ok].min())), float(max(f[ok].max(), y[ok].max()))
        ax.plot([lo, hi], [lo, hi], "r-", lw=0.8)
    if ok.any():
        _log_ticks(ax.xaxis)
        _log_ticks(ax.yaxis)
    ax.set_xlabel("fitted BRDF (1/sr)")
    ax.set_ylabel("measured BRDF (1/sr)")
    ax.set_title(f"{channel}: measured vs fitted (red: identity)", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_uncertainty_budget(material_fit, path) -> Path:
    """The uncertainty budget of every channel: per channel a table (value, the
    standard uncertainty of each component, combined, coverage factor, 95 % interval;
    rotation in degrees) and bars of each component's share of the combined variance."""
    from glossrig.core.fitting.uncertainty import COMPONENTS, PARAM_NAMES, significant_digits

    plt = _plt()
    fits = [(c, f) for c, f in material_fit.fits.items() if f.uncertainty]
    n = max(1, len(fits))
    fig, axes = plt.subplots(n, 2, figsize=(15, 2.3 * n + 0.8), squeeze=False, layout="constrained",
                             gridspec_kw={"width_ratios": [3.2, 1]})
    colours = {"noise": "tab:blue", "model": "tab:orange", "footprint": "tab:green", "calibration": "tab:red"}

    def fmt(v, deg, digits=3):
        if v is None:
            return "-"
        return f"{np.degrees(v):.{digits}g} deg" if deg else f"{v:.{digits}g}"

    for row, (c, f) in enumerate(fits):
        unc = f.uncertainty
        comps = [k for k in COMPONENTS if any(k in unc[p]["components"] for p in PARAM_NAMES)]
        cells = []
        for p in PARAM_NAMES:
            e, deg = unc[p], p == "lobe_rotation"
            iv = e["interval95"]
            n = significant_digits(e["value"], e["combined"])
            cells.append([fmt(e["value"], deg, n)] + [fmt(e["components"].get(k), deg) for k in comps]
                         + [fmt(e["combined"], deg), f"{e['coverage_factor']:.2f}",
                            "-" if iv is None else f"[{fmt(iv[0], deg, n)}, {fmt(iv[1], deg, n)}]"])
        ax = axes[row, 0]
        ax.axis("off")
        widths = [0.11] + [0.1] * len(comps) + [0.1, 0.05, 0.25]
        tab = ax.table(cellText=cells, rowLabels=list(PARAM_NAMES),
                       colLabels=["value"] + [f"u {k}" for k in comps] + ["u combined", "k", "95 % interval"],
                       colWidths=[w / sum(widths) * 0.9 for w in widths], loc="center", cellLoc="center")
        tab.auto_set_font_size(False)
        tab.set_fontsize(8)
        tab.scale(1, 1.25)
        omitted = ", ".join(sorted(unc.get("budget", {}).get("omitted", {}))) or "none"
        ax.set_title(f"{c}: uncertainty budget (standard uncertainties; omitted: {omitted})", fontsize=9)
        ax = axes[row, 1]
        left = np.zeros(len(PARAM_NAMES))
        for k in comps:
            share = []
            for p in PARAM_NAMES:
                e = unc[p]
                u, uc = e["components"].get(k), e["combined"]
                share.append((u / uc) ** 2 if (u is not None and uc) else 0.0)
            ax.barh(range(len(PARAM_NAMES)), share, left=left, color=colours.get(k, "0.5"), label=k)
            left += np.array(share)
        ax.set_yticks(range(len(PARAM_NAMES)))
        ax.set_yticklabels(PARAM_NAMES, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel("share of combined variance", fontsize=8)
        if row == 0:
            ax.legend(fontsize=7, ncol=2, loc="lower center", bbox_to_anchor=(0.5, 1.0))
    if not fits:
        axes[0, 0].text(0.5, 0.5, "no uncertainty budget in this fit", ha="center")
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
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
    if any(f.uncertainty for f in material_fit.fits.values()):
        written.append(plot_uncertainty_budget(material_fit, out / "uncertainty_budget.png"))
    return written

