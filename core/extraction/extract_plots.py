"""Diagnostic images of an extraction a user looks at: the sample mask, an HDR image
per LED (OpenEXR + tone-mapped PNG) and the samples' coverage of the BRDF space."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd


def _block_image(df: pd.DataFrame, cols) -> np.ndarray:
    u = (df.u.to_numpy() // 2)
    v = (df.v.to_numpy() // 2)
    u0, v0 = u.min(), v.min()
    img = np.zeros((v.max() - v0 + 1, u.max() - u0 + 1, len(cols)), np.float32)
    for k, c in enumerate(cols):
        img[v - v0, u - u0, k] = df[c].to_numpy()
    return img


def _png(img: np.ndarray, path: Path) -> None:
    from PIL import Image

    x = np.nan_to_num(img, nan=0.0)
    x = x / max(np.percentile(x, 99.5), 1e-12)
    x = np.clip(x / (1 + x) * 2, 0, 1) ** (1 / 2.2)          # Reinhard-ish, display gamma
    Image.fromarray((x * 255).astype(np.uint8)).save(path)


def write_plots(folder: Path, measured: pd.DataFrame, samples: pd.DataFrame) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    for (rot, led), sub in measured.groupby(["rotation", "led"]):
        img = _block_image(sub, ["r", "g", "b"])
        tag = f"r{rot:+.0f}_led{int(led):02d}"
        _png(img, folder / f"hdr_{tag}.png")
        try:
            import OpenEXR

            OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": img}).write(str(folder / f"hdr_{tag}.exr"))
        except Exception:   # OpenEXR is a dependency; a failure here must not lose the extraction
            pass
    for rot, sub in measured.groupby("rotation"):
        m = _block_image(sub.drop_duplicates(["u", "v"]).assign(one=1.0), ["one"])[..., 0]
        from PIL import Image

        Image.fromarray((m * 255).astype(np.uint8)).save(folder / f"sample_mask_r{rot:+.0f}.png")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for led, sub in samples.groupby("led"):
        s = sub.sample(min(len(sub), 4000), random_state=0)
        axes[0].scatter(np.degrees(s.theta_in), np.degrees(s.theta_out), s=1, label=f"LED {led}")
        axes[1].scatter(np.degrees(s.theta_h), np.degrees(s.theta_d), s=1)
    axes[0].set(xlabel="theta_in (deg)", ylabel="theta_out (deg)", title="coverage: in/out zenith")
    axes[1].set(xlabel="theta_h (deg)", ylabel="theta_d (deg)", title="coverage: half/difference")
    axes[0].legend(markerscale=6, fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "coverage.png", dpi=110)
    plt.close(fig)
