"""Figures of the measurement report (issue 17) that :mod:`glossrig.core.fitting.fit_plots` lacks.

* :func:`hdr_per_led` / :func:`plot_hdr_per_led` - the HDR image of every LED of a
  capture (thesis 4.3.3: eq. 4.31 repeats, 4.32-4.38 neighbour correction, then the
  project's maximum-likelihood rate :func:`glossrig.core.radiometry.hdr.hdr_ml`), tone-mapped by
  ``log10`` of the rate on one colour scale shared by all LEDs, with a labelled colour
  bar; saturated and too-dark pixels are marked, and the saturation statistics feed
  the report's capture section.
* :func:`plot_coverage` - the samples in (theta_h, theta_d) (Rusinkiewicz, EGWR 1998)
  and (theta_in, theta_out), per LED, with the 1-degree bin coverage of thesis 7.1.3
  (:func:`glossrig.core.design.coverage.bin_codes`).
* :func:`plot_incidence_slices` - BRDF against theta_out at fixed theta_in in the
  plane of incidence, measured and fitted (thesis fig. 7.1).
* :func:`plot_polar_lobe` - the fitted lobe in polar form in the two planes of
  incidence that hold the lobe's principal axes (eq. 4.79-4.80).

All figures: matplotlib Agg, constrained layout (no overlapping labels), PNG at
``DPI`` dots per inch, every axis labelled with its unit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from glossrig.core.models.angles import local_direction
from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams, ward_local

DPI = 110


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    plt = _plt()
    path = Path(path)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- HDR per LED

@dataclass
class LedHdr:
    """The HDR of one (rotation, LED) sequence, at half resolution (2x2 Bayer blocks).

    ``image``: mean rate of the block's four CFA pixels, ``(R + 2 G + B) / 4`` in
    camera RGB (not white-balanced), in fractions of the sensor's white-black range
    per second of exposure (:class:`glossrig.core.radiometry.hdr.HdrResult`); NaN where no pixel
    of the block is valid. ``saturated`` / ``dark``: blocks with a pixel too bright
    even at the shortest exposure / too dark even at the longest."""

    led: int
    rotation: float
    image: np.ndarray
    saturated: np.ndarray
    dark: np.ndarray
    exposures_s: list[float]
    repeats: int
    files: int
    saturated_at_shortest: float      # fraction of pixels at the white level in the shortest exposure
    saturated_at_longest: float       # ... in the longest exposure
    status_counts: dict[str, int] = field(default_factory=dict)
    pixels_per_block: int = 2         # image pixels per block side (2, or 2 x the decimation step)


def _blocks(a: np.ndarray, how: str) -> np.ndarray:
    h, w = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    b = a[:h, :w].reshape(h // 2, 2, w // 2, 2)
    if how == "any":
        return b.any(axis=(1, 3))  # type: ignore[return-value]  # numpy's stubs type any(axis=...) as bool | array
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmean(b, axis=(1, 3)).astype(np.float32)


def decimate_blocks(frame, step: int):
    """The frame with every ``step``-th 2x2 Bayer block kept in each direction: the
    CFA pattern, levels and metadata stay valid (whole blocks are kept), so the HDR of
    the result is the HDR of those blocks. Keeps a full-resolution capture's stacks
    small (a 24 Mpx frame is 96 MB as float32, times the 18 exposures)."""
    from dataclasses import replace

    if step <= 1:
        return frame
    m = frame.mosaic
    h, w = (m.shape[0] // 2) * 2, (m.shape[1] // 2) * 2
    b = m[:h, :w].reshape(h // 2, 2, w // 2, 2)[::step, :, ::step, :]
    return replace(frame, mosaic=np.ascontiguousarray(b.reshape(b.shape[0] * 2, b.shape[2] * 2)))


def hdr_per_led(sample_dir, *, rotation: float | None = None, leds=None, max_width: int = 1600,
                log=None) -> list[LedHdr]:
    """HDR image of every LED of a capture at one sample rotation (default: the first).

    Reads every sequence image through the manifest (checksums verified), combines
    the repeats (eq. 4.31), corrects the LED jitter (eq. 4.32-4.38, robust) and
    estimates the rate with :func:`glossrig.core.radiometry.hdr.hdr_ml` under the rig's noise
    model - the extraction's own radiometry (:func:`glossrig.core.extraction.extract.led_values`)
    on the full frame instead of the sample crop, and without patch normalisation (so
    the images show what the camera recorded). Frames wider than ``max_width`` pixels
    are decimated by whole Bayer blocks first (:func:`decimate_blocks`): the figure
    shows about 700 px per LED, and the HDR of a kept pixel does not depend on the
    others."""
    from glossrig.core.radiometry import hdr as hdrmod
    from glossrig.core.capture import load_manifest
    from glossrig.core.rig import load_rig

    man = load_manifest(sample_dir)
    man.require_sequences("the report's HDR images", "SAMPLE_DIR")
    rig = load_rig(man.rig_path())
    rots = man.rotations()
    rot = rots[0] if rotation is None else float(rotation)
    if rot not in rots:
        raise InputError(f"no sequence at rotation {rot:g} deg (have {', '.join(f'{r:g}' for r in rots)})",
                         path=man.path)
    seqs = man.select("sequence", rotation=rot)
    have = sorted({im.leds[0] for im in seqs})
    want = have if leds is None else [int(x) for x in leds if int(x) in have]
    out = []
    for led in want:
        seq = [im for im in seqs if im.leds == [led]]
        frames = []
        step = 1
        for im in seq:
            f = man.read_raw(im)
            step = max(1, math.ceil(f.mosaic.shape[1] / max_width))
            frames.append(decimate_blocks(f, step))
        stack = hdrmod.stack_frames(frames, [im.repeat for im in seq])
        res = hdrmod.hdr_from_stack(stack, hdrmod.NoiseModel.from_rig(rig, iso=seq[0].iso))
        sat_short = float(stack.clipped[0].mean())
        sat_long = float(stack.clipped[-1].mean())
        out.append(LedHdr(led=led, rotation=rot, image=_blocks(res.rate, "mean"),
                          saturated=_blocks(res.status == hdrmod.TOO_BRIGHT, "any"),
                          dark=_blocks(res.status == hdrmod.TOO_DARK, "any"),
                          exposures_s=[float(t) for t in stack.exposure_s], repeats=int(stack.repeats),
                          files=len(seq), saturated_at_shortest=sat_short, saturated_at_longest=sat_long,
                          status_counts=res.reason_counts(), pixels_per_block=2 * step))
        if log:
            log(f"HDR of LED {led} at rotation {rot:g} deg")
    return out


def hdr_colour_range(hdrs: list[LedHdr], decades: float = 5.0) -> tuple[float, float]:
    """The shared log10 range of the tone map: from the 0.5th to the 99.9th percentile
    of every valid rate of every LED, at most ``decades`` wide (cut at the bottom)."""
    vals = np.concatenate([h.image[np.isfinite(h.image) & (h.image > 0)].ravel() for h in hdrs] or [np.zeros(0)])
    if vals.size == 0:
        return -3.0, 0.0
    lo, hi = np.log10(np.percentile(vals, [0.5, 99.9]))
    if not hi > lo:
        hi = lo + 1.0
    return float(max(lo, hi - decades)), float(hi)


def plot_hdr_per_led(hdrs: list[LedHdr], path, *, ncols: int = 2, panel_width_in: float = 6.4) -> Path:
    """Every LED's HDR image, ``log10`` tone map on one shared scale (see
    :func:`hdr_colour_range`), one colour bar; saturated blocks magenta, too-dark
    blocks black. Panels of ``panel_width_in`` inches (>= 700 px at ``DPI``)."""
    plt = _plt()
    from matplotlib import colors

    if not hdrs:
        raise InputError("no HDR images to plot")
    lo, hi = hdr_colour_range(hdrs)
    n = len(hdrs)
    ncols = max(1, min(ncols, n))
    nrows = math.ceil(n / ncols)
    h, w = hdrs[0].image.shape
    panel_h = panel_width_in * h / w + 0.5
    fig, axes = plt.subplots(nrows, ncols, figsize=(panel_width_in * ncols + 1.3, panel_h * nrows + 0.6),
                             squeeze=False, layout="constrained")
    cmap = plt.get_cmap("inferno").with_extremes(bad="black", under="black")
    im = None
    for ax, hd in zip(axes.flat, hdrs):
        with np.errstate(divide="ignore", invalid="ignore"):
            lg = np.log10(np.where(hd.image > 0, hd.image, np.nan))
        im = ax.imshow(lg, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        if hd.saturated.any():
            over = np.zeros(hd.saturated.shape + (4,), np.float32)
            over[hd.saturated] = colors.to_rgba("magenta")
            ax.imshow(over, interpolation="nearest")
        ax.set_title(f"LED {hd.led}, rotation {hd.rotation:g} deg: saturated {100 * hd.saturated.mean():.2f} %, "
                     f"too dark {100 * hd.dark.mean():.1f} % of blocks", fontsize=9)
        ax.set_xlabel(f"image x (blocks of {hd.pixels_per_block} px)")
        ax.set_ylabel(f"image y (blocks of {hd.pixels_per_block} px)")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    cb = fig.colorbar(im, ax=axes, shrink=0.9, extend="both", aspect=40)
    cb.set_label("log10 HDR rate (fraction of white-black range per s)")
    fig.suptitle(f"HDR per LED: log10 tone map, shared scale {lo:.1f} .. {hi:.1f}; black = too dark or invalid, "
                 "magenta = saturated even at the shortest exposure", fontsize=10)
    return _save(fig, path)


# --------------------------------------------------------------------------- coverage

def coverage_stats(df) -> dict:
    """1-degree bin coverage of the samples (thesis 7.1.3, convention "lit, dphi folded"
    of :mod:`glossrig.core.design.coverage`): occupied bins over all bins of the isotropic
    (theta_in, theta_out, |phi_in - phi_out|) and anisotropic (theta_in, theta_out,
    phi_in, phi_out) spaces."""
    from glossrig.core.design.coverage import Convention, bin_codes

    deg = {k: np.degrees(np.asarray(df[k], float)) for k in ("theta_in", "theta_out", "phi_in", "phi_out")}
    codes = bin_codes(deg["theta_in"], deg["theta_out"], deg["phi_in"], deg["phi_out"])
    conv = Convention()
    return {"n_samples": int(len(df)), "leds": sorted(int(x) for x in np.unique(np.asarray(df["led"]))),
            "rotations": sorted(float(x) for x in np.unique(np.asarray(df["rotation"], float))),
            "isotropic": len(codes["iso_folded"]) / conv.iso_total(),
            "anisotropic": len(codes["aniso"]) / conv.aniso_total(),
            "isotropic_bins": int(len(codes["iso_folded"])), "anisotropic_bins": int(len(codes["aniso"])),
            "convention": conv.label(),
            "theta_d_max_deg": float(np.degrees(np.max(np.asarray(df["theta_d"], float)))),
            "theta_h_max_deg": float(np.degrees(np.max(np.asarray(df["theta_h"], float))))}


def plot_coverage(df, path, *, max_points: int = 6000) -> Path:
    """Samples in (theta_h, theta_d) and (theta_in, theta_out), coloured by LED."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 5.4), layout="constrained")
    leds = sorted(int(x) for x in np.unique(np.asarray(df["led"])))
    cmap = plt.get_cmap("tab20" if len(leds) > 10 else "tab10")
    led_col = np.asarray(df["led"])
    rng = np.random.default_rng(0)
    for k, led in enumerate(leds):
        idx = np.flatnonzero(led_col == led)
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        c = cmap(k % cmap.N)
        sub = {n: np.degrees(np.asarray(df[n], float)[idx]) for n in ("theta_h", "theta_d", "theta_in", "theta_out")}
        axes[0].scatter(sub["theta_h"], sub["theta_d"], s=2, color=c, lw=0, rasterized=True, label=f"LED {led}")
        axes[1].scatter(sub["theta_in"], sub["theta_out"], s=2, color=c, lw=0, rasterized=True)
    axes[0].set(xlabel=r"$\theta_h$ (deg)", ylabel=r"$\theta_d$ (deg)", xlim=(0, 90), ylim=(0, 90),
                title="half / difference angles (Rusinkiewicz)")
    axes[1].set(xlabel=r"$\theta_{in}$ (deg)", ylabel=r"$\theta_{out}$ (deg)", xlim=(0, 90), ylim=(0, 90),
                title="incident / outgoing zenith")
    axes[1].plot([0, 90], [0, 90], color="0.6", lw=0.8, ls=":")
    for ax in axes:
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    axes[0].legend(markerscale=6, fontsize=8, loc="upper right", ncol=2 if len(leds) > 6 else 1)
    st = coverage_stats(df)
    fig.suptitle(f"BRDF-space coverage: {st['n_samples']} samples; 1-degree bins occupied: isotropic "
                 f"{100 * st['isotropic']:.3g} %, anisotropic {100 * st['anisotropic']:.3g} % (thesis 7.1.3)",
                 fontsize=10)
    return _save(fig, path)


# --------------------------------------------------------------------------- incidence plane

def signed_in_plane(df) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the angle (radians) of the outgoing direction out of the plane of
    incidence, ``asin(sin theta_out |sin(phi_out - phi_in)|)``, and the signed outgoing
    zenith, positive on the mirror side (``cos(phi_out - phi_in) < 0``, i.e. phi_out
    near phi_in + 180 deg), negative on the light's side (back-scatter)."""
    to = np.asarray(df["theta_out"], float)
    dphi = np.asarray(df["phi_out"], float) - np.asarray(df["phi_in"], float)
    out_of_plane = np.arcsin(np.clip(np.sin(to) * np.abs(np.sin(dphi)), 0, 1))
    signed = np.where(np.cos(dphi) < 0, to, -to)
    return out_of_plane, signed


def model_in_plane(p: WardParams, theta_in: float, phi_in: float, signed_theta_out) -> np.ndarray:
    """Eq. 4.79 in the plane of incidence: light at (theta_in, phi_in), camera at
    ``|signed_theta_out|`` on the mirror side (phi_in + pi) when positive, on the
    light's side (phi_in) when negative."""
    s = np.asarray(signed_theta_out, float)
    wi = local_direction(theta_in, phi_in)
    wo = local_direction(np.abs(s), np.where(s >= 0, phi_in + np.pi, phi_in))
    return ward_local(np.broadcast_to(wi, wo.shape), wo, p)


def _circ_mean(a: np.ndarray) -> float:
    return float(np.mod(np.arctan2(np.mean(np.sin(a)), np.mean(np.cos(a))), 2 * np.pi))


def incidence_bins(theta_in_deg: np.ndarray, n: int = 6, half_width: float = 2.0,
                   taken: list[float] | None = None) -> list[float]:
    """Centres (deg, whole degrees) of up to ``n`` theta_in bins of +-``half_width``
    spread over the measured range (quantiles), at least 2 half-widths apart from each
    other and from the centres already ``taken`` (which are not returned)."""
    taken = list(taken or [])
    if theta_in_deg.size == 0 or n <= 0:
        return []
    qs = np.round(np.quantile(theta_in_deg, np.linspace(0.08, 0.92, max(n, 2))))
    centres: list[float] = []
    for q in qs:
        if len(centres) < n and all(abs(q - c) >= 2 * half_width for c in centres + taken):
            centres.append(float(q))
    return centres


def plot_incidence_slices(df, fit, path, *, channel: str | None = None, truth: WardParams | None = None,
                          tolerances_deg=(2.0, 4.0, 8.0), half_width_deg: float = 2.0, min_samples: int = 200,
                          max_panels: int = 6) -> Path:
    """BRDF against the signed theta_out at fixed theta_in, in the plane of incidence
    (thesis fig. 7.1): samples whose outgoing direction lies within a tolerance of the
    plane of incidence (the smallest of ``tolerances_deg`` that keeps ``min_samples``),
    in bins of theta_in of +-``half_width_deg``; one panel per bin with the fitted
    model (solid) at the bin's centre theta_in and circular-mean phi_in - the lobe is
    anisotropic, so the curve holds for that azimuth - and the truth (dashed) when
    given. ``fit``: an object with ``channel``, ``params`` (:class:`WardParams`),
    ``clip``."""
    from glossrig.core.fitting.fit import channel_values

    plt = _plt()
    channel = channel or fit.channel
    y = channel_values(df, channel)
    off, signed = signed_in_plane(df)
    ti = np.asarray(df["theta_in"], float)
    phi_in = np.asarray(df["phi_in"], float)
    tol = tolerances_deg[-1]
    for t in tolerances_deg:
        if np.sum(off < np.radians(t)) >= min_samples:
            tol = t
            break
    near = off < np.radians(tol)
    # bins where the mirror side was seen first (they hold the specular lobe), then the rest
    mirror = near & (signed > 0)
    centres = incidence_bins(np.degrees(ti[mirror]), min(4, max_panels), half_width_deg) \
        if mirror.sum() >= 50 else []
    centres = sorted(centres + incidence_bins(np.degrees(ti[near]), max_panels - len(centres), half_width_deg,
                                              taken=centres))
    n = max(1, len(centres))
    ncols = min(3, n)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.6 * ncols + 0.4, 3.9 * nrows + 0.7), squeeze=False,
                             layout="constrained")
    xs = np.radians(np.linspace(-89.5, 89.5, 719))
    for ax, c in zip(axes.flat, centres):
        m = near & (np.abs(np.degrees(ti) - c) <= half_width_deg)
        x = np.degrees(signed[m])
        ax.scatter(x, y[m], s=3, c="0.35", lw=0, alpha=0.5, rasterized=True, label=f"measured (n={m.sum()})")
        ph = _circ_mean(phi_in[m]) if m.any() else 0.0
        ax.plot(np.degrees(xs), model_in_plane(fit.params, math.radians(c), ph, xs), "-", color="tab:red", lw=1.4,
                label="fitted model")
        if truth is not None:
            ax.plot(np.degrees(xs), model_in_plane(truth, math.radians(c), ph, xs), "--", color="tab:blue", lw=1.1,
                    label="truth")
        ax.axvline(c, color="0.5", lw=0.8, ls=":")
        lo, hi = (min(x.min(), c), max(x.max(), c)) if x.size else (-60.0, 60.0)
        pad = max(5.0, 0.1 * (hi - lo))
        ax.set_xlim(max(-90, lo - pad), min(90, hi + pad))
        ax.set_yscale("log")
        ax.set_title(rf"$\theta_{{in}}$ = {c:g} $\pm$ {half_width_deg:g} deg, $\phi_{{in}}$ = "
                     f"{round(math.degrees(ph)) % 360:d} deg", fontsize=9)
        ax.set_xlabel(r"signed $\theta_{out}$ (deg), + on the mirror side")
        ax.set_ylabel(f"BRDF, {channel} (1/sr)")
        ax.grid(alpha=0.3, which="both")
    if not centres:
        axes[0, 0].text(0.5, 0.5, "no samples near the plane of incidence", transform=axes[0, 0].transAxes,
                        ha="center")
        axes[0, 0].set_xlabel(r"signed $\theta_{out}$ (deg), + on the mirror side")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0, 0].set_ylabel(f"BRDF, {channel} (1/sr)")
    axes[0, 0].legend(fontsize=8, loc="lower center", markerscale=4)
    fig.suptitle(f"{channel}: plane of incidence (samples within {tol:g} deg of it); dotted: the mirror "
                 r"direction $\theta_{out} = \theta_{in}$", fontsize=10)
    return _save(fig, path)


def plot_polar_lobe(fit, path, *, truth: WardParams | None = None, theta_in_deg=(15, 30, 45, 60)) -> Path:
    """The fitted lobe in polar form (eq. 4.79-4.80): radius ``log10`` of the BRDF
    (1/sr), angle the signed outgoing zenith (mirror side to the right), for the light
    at each of ``theta_in_deg`` (marked on the rim, left), in the two planes of
    incidence that contain the lobe's principal axes: its x (wide) axis, where
    ``phi_h + lobe_rotation`` = 0 (the light at azimuth ``-lobe_rotation``), and its y
    axis (azimuth ``pi/2 - lobe_rotation``). The truth, when given, dashed."""
    plt = _plt()
    p = fit.params
    fig, axes = plt.subplots(1, 2, figsize=(13.5, 4.2), subplot_kw={"projection": "polar"}, layout="constrained")
    xs = np.radians(np.linspace(-89.5, 89.5, 719))
    cmap = plt.get_cmap("viridis")
    curves = []
    for ax, (name, ph) in zip(axes, (("x (wide) axis", -p.lobe_rotation),
                                     ("y (narrow) axis", math.pi / 2 - p.lobe_rotation))):
        for k, t in enumerate(theta_in_deg):
            f = model_in_plane(p, math.radians(t), ph, xs)
            curves.append(f)
            c = cmap(k / max(1, len(theta_in_deg) - 1))
            ax.plot(xs, np.log10(np.maximum(f, 1e-12)), color=c, lw=1.5, label=rf"$\theta_{{in}}$ = {t} deg")
            if truth is not None:
                ft = model_in_plane(truth, math.radians(t), ph, xs)
                ax.plot(xs, np.log10(np.maximum(ft, 1e-12)), color=c, lw=1.0, ls="--")
        ax.set_title(f"plane of the lobe's {name} (light azimuth {math.degrees(ph) % 360:.0f} deg)", fontsize=10)
        ax.set_theta_zero_location("N")
        ax.set_theta_direction(-1)
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
    allf = np.concatenate(curves)
    top = float(np.log10(np.max(allf)))
    # the diffuse floor sits 0.6 decade above the centre, so it shows as a half circle
    bottom = float(np.log10(max(np.min(allf[allf > 0]) if (allf > 0).any() else 1e-3, 10 ** (top - 4)))) - 0.6
    from matplotlib.ticker import MaxNLocator

    for ax in axes:
        for k, t in enumerate(theta_in_deg):
            ax.plot([-math.radians(t)], [top + 0.1], marker="o", ms=6, color=cmap(k / max(1, len(theta_in_deg) - 1)),
                    clip_on=False)
        ax.set_rlim(bottom, top + 0.15)          # after the last plot call, which would autoscale
        ax.yaxis.set_major_locator(MaxNLocator(4))
        ax.tick_params(axis="y", labelsize=8)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right upper", fontsize=9)
    fig.suptitle(r"fitted lobe, polar: angle = signed $\theta_{out}$ (deg), mirror side to the right; radius = "
                 "log10 BRDF (1/sr); dots on the rim: light directions" + ("; dashed: truth" if truth else ""),
                 fontsize=10)
    return _save(fig, path)
