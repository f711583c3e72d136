"""report.json and report.md with the residual plots (issue 7, step 5)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from glossrig.core.atomic import atomic_write_text
from glossrig.core.diagnose.catalogue import THRESHOLDS, CauseResult

#: spaces where a cause acts on the raw frames themselves, looked at first
SENSOR_SPACES = ("frames", "pixels")
#: share of the flexible material model's gain a named material model must reach to be named instead
NAMED_SHARE = 0.5


def verdict(causes: list[CauseResult]) -> str:
    """The significant cause with the largest gain, sensor-level causes first.

    A sensor cause (black offset, non-linearity, LED drift within a sequence, hot pixels)
    bends each pixel's exposure series or puts the same spike under every LED; light and
    geometry causes (stray light, vignetting, LED emission and position, sample radius and
    rotation) scale or offset whole frames and leave every exposure series linear, so they
    cannot produce a frame- or pixel-space discrepancy. The converse is not true: a sensor
    cause also distorts the BRDF (measured: a 1 % non-linearity gave stray light a 6.8 %
    BRDF-space gain). So frame- and pixel-space evidence decides first; BRDF-space gains,
    on another error scale, name the cause only when the frames are clean.

    Only *eligible* causes count (issue 14): a BRDF-space instrument cause that does not beat
    the flexible material model on held-out folds is blocked (:mod:`.flexible`); a named
    material model is preferred to the flexible one when it reaches NAMED_SHARE of its gain."""
    sig = [c for c in causes if c.eligible]
    sensor = [c for c in sig if c.space in SENSOR_SPACES]
    pick = sensor or sig
    if not pick:
        return "none"
    best = max(pick, key=lambda c: c.gain)
    if best.name == "flexible_material":
        # a named material model (GGX, Beckmann, grazing lobe, Fresnel) is preferred to the flexible
        # one when it reaches NAMED_SHARE of its gain: it says what the material is, with parameters
        named = [c for c in sig if c.kind == "material" and c.name != best.name and c.gain >= NAMED_SHARE * best.gain]
        if named:
            return max(named, key=lambda c: c.gain).name
    return best.name


def residual_after(entry: dict) -> str:
    """The model whose residual an open-world entry tested: its ``after`` (a named cause tested
    again), else the baseline of its space - the flexible material model in BRDF space, the
    linear sensor in frame space (:mod:`glossrig.core.diagnose.unexplained`)."""
    return entry.get("after") or ("flexible_material" if entry.get("space") == "brdf" else "linear sensor")


def final_verdict(causes: list[CauseResult], entries: list[dict]) -> str:
    """The report's verdict: :func:`verdict` of the causes, overruled by "unexplained" where the
    open-world structure tests ``entries`` (:func:`glossrig.core.diagnose.unexplained.unexplained`)
    say so (:func:`glossrig.core.diagnose.unexplained.open_world_verdict`)."""
    from glossrig.core.diagnose.unexplained import open_world_verdict

    v = verdict(causes)
    return open_world_verdict(v, next((c.kind for c in causes if c.name == v), None), entries)


def _plots(out: Path, structure: dict, causes: list[CauseResult]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for space, st in structure.items():
        n = len(st)
        fig, axs = plt.subplots(1, n, figsize=(3.2 * n, 2.8), squeeze=False)
        for ax, (k, b) in zip(axs[0], st.items()):
            ax.plot(b["x"], b["mean"], "o-", ms=3)
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(k, fontsize=8)
            ax.tick_params(labelsize=7)
        axs[0][0].set_ylabel("mean normalised residual", fontsize=8)
        fig.tight_layout()
        f = f"residuals_{space}.png"
        fig.savefig(out / f, dpi=90)
        plt.close(fig)
        files.append(f)
    prof = [c for c in causes if c.profile]
    if prof:
        fig, axs = plt.subplots(1, len(prof), figsize=(3.2 * len(prof), 2.8), squeeze=False)
        for ax, c in zip(axs[0], prof):
            assert c.profile is not None        # prof holds only causes with a profile
            ax.plot(c.profile["grid"], c.profile["error"], "-")
            ax.axhline(c.base_error, color="r", lw=0.7, ls="--")
            ax.set_title(f"{c.name} ({c.space})", fontsize=8)
            ax.set_xlabel(next(k for k in c.params if k not in ("unit", "fold_estimates")), fontsize=8)
            ax.tick_params(labelsize=7)
        axs[0][0].set_ylabel("held-out error (base dashed)", fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "profiles.png", dpi=90)
        plt.close(fig)
        files.append("profiles.png")
    return files


def read_report(path) -> dict:
    """A diagnosis report (``report.json`` written by :func:`write_report`; ``path``: the
    file or the report folder): the one reader of the file. Refuses, naming the file, one
    that is missing, not JSON or without the ``verdict`` and the ``causes`` list."""
    from glossrig.core.errors import InputError
    from glossrig.core.toml_input import read_json

    path = Path(path)
    if path.is_dir():
        path = path / "report.json"
    d = read_json(path, "diagnosis report")
    if not isinstance(d, dict) or not isinstance(d.get("verdict"), str) or not isinstance(d.get("causes"), list):
        raise InputError("not a glossrig diagnose report (expected \"verdict\" and \"causes\")", path=path)
    return d


def _num(x):
    if isinstance(x, dict):
        return {k: _num(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_num(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_report(out, causes: list[CauseResult], base_errors: dict, structure: dict, meta: dict,
                 plots: bool = True, unexplained: list | None = None, calibration: dict | None = None) -> dict:
    """``unexplained``: the open-world structure tests (:func:`glossrig.core.diagnose.unexplained.unexplained`);
    ``calibration``: the base model's held-out error with the calibrated error model."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    causes = sorted(causes, key=lambda c: c.gain, reverse=True)
    unexplained = unexplained or []
    v = final_verdict(causes, unexplained)
    rep = {"base_error": base_errors.get("brdf"), "base_errors": base_errors, "verdict": v,
           "calibration": calibration or {},
           "unexplained": [{"variable": e["variable"], "effect": e["effect"], "significant": e["significant"],
                            "space": e.get("space"), "p": e.get("p"), "effect_unit": e.get("effect_unit"),
                            "after": residual_after(e),
                            "profile": e.get("profile")} for e in unexplained],
           "penalty": {"per_space": {k: {"gain_threshold": t, "per_extra_parameter": p}
                                     for k, (t, p) in THRESHOLDS.items()},
                       "rule": "significant iff held-out error drops in every fold and the pooled relative gain "
                               "exceeds gain_threshold + per_extra_parameter * extra parameters of its space; "
                               "the verdict is the largest significant gain, frame/pixel-space causes first; "
                               "a BRDF-space instrument cause must also beat the flexible material model "
                               "(eligible); 'unexplained' when significant residual structure remains that no "
                               "eligible cause explains"},
           "causes": [c.to_json() for c in causes], "residual_structure": structure, "meta": meta}
    rep = _num(rep)
    atomic_write_text(out / "report.json", json.dumps(rep, indent=1))
    files = _plots(out, structure, causes) if plots else []
    L = ["# glossrig diagnose report", "", f"Sample: `{meta.get('sample')}`  ", f"Reference: `{meta.get('reference')}`  ",
         f"Material (Ward fit, luminance): {meta.get('material')}", "",
         f"## Verdict: **{v}**", ""]
    if v == "none":
        L.append("No cause lowers the held-out error by more than the stated threshold in every fold: "
                 "no significant discrepancy between the measurement and the model.")
    elif v == "unexplained":
        L.append("Structured residual remains that no catalogue cause explains: "
                 + ", ".join(f"{e['variable']} (effect {e['effect']:.3g} {e.get('effect_unit', '')}"
                             + (f", after {e['after']}" if e.get("after") else "") + ")"
                             for e in unexplained if e["significant"]) + ".")
    else:
        w = next(c for c in causes if c.name == v)
        L.append(f"`{v}` lowers the held-out error of the {w.space}-space model from {w.base_error:.4g} to "
                 f"{w.error:.4g} (gain {w.gain:.1%}); parameters {json.dumps(_num(w.params))} "
                 f"+- {json.dumps(_num(w.stderr))} (statistical only - noise or fold spread; excludes calibration "
                 "and model error, so not the parameters' full uncertainty).")
    if calibration:
        L += ["", f"Calibrated error model: base model's normalised held-out error "
              f"{calibration.get('heldout_error', float('nan')):.3g} (noise alone "
              f"{calibration.get('heldout_error_noise_only', float('nan')):.3g}); 1 means the model-error "
              "term fitted on the training folds and the HDR noise describe the held-out data."]
    L += ["", "Base held-out errors (mean squared normalised residual): "
          + ", ".join(f"{k} {val:.4g}" for k, val in base_errors.items()), "",
          "Penalty: a cause is significant when its held-out error is lower in every fold and the pooled gain "
          "exceeds its space's threshold plus a penalty per extra parameter ("
          + "; ".join(f"{k}: {t:.2%} + {p:.2%}" for k, (t, p) in THRESHOLDS.items())
          + "). Sensor-level (frames, pixels) causes are named first: light and geometry causes cannot bend "
          "the raw exposure series.", "",
          "| cause | space | gain | threshold | eligible | params | note |", "|---|---|---|---|---|---|---|"]
    for c in causes:
        p = {k: val for k, val in _num(c.params).items() if k not in ("fold_estimates", "profile")}
        L.append(f"| {c.name} ({c.kind}) | {c.space} | {c.gain:.2%} | {c.threshold:.2%} | {c.eligible} | "
                 f"`{json.dumps(p)}` | {c.note} |")
    if unexplained:
        L += ["", "## Residual structure no cause explains", "",
              "| variable | space | residual after | effect | p | significant |", "|---|---|---|---|---|---|"]
        L += [f"| {e['variable']} | {e.get('space')} | "
              f"{residual_after(e)} | "
              f"{e['effect']:.3g} | {e.get('p', float('nan')):.2g} | {e['significant']} |" for e in unexplained]
    L += ["", "## Causes and their physics", ""]
    for c in causes:
        L += [f"* **{c.name}**: {c.doc}"]
    L += ["", "## Residual structure", ""]
    for f in files:
        L.append(f"![{f}]({f})")
    atomic_write_text(out / "report.md", "\n".join(L) + "\n")
    return rep
