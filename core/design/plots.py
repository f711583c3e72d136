"""Figures of the LED design report (``glossrig design optimise --report``): score and
coverage against the number of LEDs, the two LED layouts, and the expected Ward-parameter
errors of each design. The coverage figures (theta per LED, coverage by rotation, per
LED) are in :mod:`glossrig.core.design.coverage`."""
from __future__ import annotations

import math


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_prefixes(res, path) -> None:
    """Score, anisotropic coverage and expected errors of the design's greedy prefixes
    (:attr:`glossrig.core.design.placement.DesignResult.prefixes`)."""
    plt = _pyplot()
    rows = res.prefixes
    n = [r["n_leds"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(n, [r["score"] for r in rows], "o-")
    ax[0].axhline(0, color="0.5", ls="--", lw=0.8)
    ax[0].set_xlabel("number of LEDs (greedy order)")
    ax[0].set_ylabel("score (thesis rig = 0)")
    ax[1].plot(n, [100 * r["anisotropic_coverage"] for r in rows], "o-", color="C3", label="anisotropic coverage")
    ax[1].axhline(100 * res.reference["anisotropic_coverage_design_scale"], color="C3", ls="--", lw=0.8,
                  label="thesis rig")
    ax[1].set_xlabel("number of LEDs (greedy order)")
    ax[1].set_ylabel("anisotropic coverage (%)")
    ax2 = ax[1].twinx()
    for lb in rows[0]["geometric_mean_relative_error"]:
        ax2.semilogy(n, [r["geometric_mean_relative_error"][lb] for r in rows], ".:", label=lb)
    ax2.set_ylabel("geometric-mean relative error")
    ax[1].legend(fontsize=7, loc="upper left")
    ax2.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_layout(ref_rig, new_rig, path) -> None:
    """Top and side views of both LED layouts with the board, camera and its field of view."""
    import numpy as np

    from glossrig.core.design import placement as D

    plt = _pyplot()
    lim = D.MountingLimits()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5.5))
    bx, bz = lim.board_x_mm, lim.board_z_mm
    ax1.add_patch(plt.Rectangle((bx[0], bz[0]), bx[1] - bx[0], bz[1] - bz[0], fill=False, ls="--", color="0.5"))
    cam = ref_rig.camera
    half = math.atan((cam.image_px[1] / 2) / cam.fy)       # across the axis (rolled camera)
    zc = cam.distance_to_axis
    for s in (-1, 1):
        ax1.plot([0, s * zc * math.tan(half) * 2], [zc, -zc], color="C2", lw=0.8)
    ax1.plot([0], [zc], "s", color="C2", label="camera")
    ax1.add_patch(plt.Circle((0, 0), ref_rig.cylinder_radius, color="0.3"))
    for rg, mk, col, lab in ((ref_rig, "o", "C0", "thesis"), (new_rig, "^", "C3", "optimised")):
        P = np.array([led.position for led in rg.leds])
        ax1.scatter(P[:, 0], P[:, 2], marker=mk, color=col, label=lab, s=30)
        ang = np.degrees(np.arctan2(P[:, 0], P[:, 2]))
        ax2.scatter(ang, P[:, 1], marker=mk, color=col, label=lab, s=30)
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (mm)")
    ax1.set_ylabel("z (mm, towards the camera)")
    ax1.set_title("Top view: board (dashed), camera field of view (green)")
    ax1.legend(fontsize=8)
    ax2.set_xlabel("angle about the axis from the camera (deg)")
    ax2.set_ylabel("height (mm)")
    ax2.axhspan(*lim.height_mm, color="0.9", zorder=0)
    ax2.set_title("Angle and height of every LED")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_errors(out: dict, materials, path) -> None:
    """Expected relative standard errors of every design (``out``: the ``design.json``
    document of :func:`glossrig.core.design.optimise_report.compare_designs`), one panel
    per material."""
    import numpy as np

    from glossrig.core.design.fisher import PARAMS

    plt = _pyplot()
    keys = [k for k in ("thesis_middle", "thesis_16", "optimised") if k in out["rigs"]]
    fig, axes = plt.subplots(1, len(materials), figsize=(4.5 * len(materials), 4), squeeze=False)
    for ax, (lb, _) in zip(axes[0], materials):
        x = np.arange(len(PARAMS))
        w = 0.8 / len(keys)
        for k, key in enumerate(keys):
            rel = out["rigs"][key]["expected_errors"][lb]["relative"]
            vals = [rel[p] if rel[p] is not None else np.nan for p in PARAMS]
            ax.bar(x + k * w, vals, width=w, label=key)
        ax.set_yscale("log")
        ax.set_xticks(x + w * (len(keys) - 1) / 2, ["rho_d", "rho_s", "a_x", "a_y", "rot (rad)"], fontsize=8)
        ax.set_title(lb, fontsize=9)
        ax.set_ylabel("expected relative standard error")
    axes[0][0].legend(fontsize=8)
    fig.suptitle("Expected Ward-parameter errors (Fisher information)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
