"""Which colour channels ran out of dynamic range in an extraction, where, and what
exposure would have fixed it (issue 14).

A block's channel has no HDR value when it is too dark even at the longest exposure or
saturated even at the shortest (:data:`glossrig.core.radiometry.hdr.STATUS_REASONS`,
per block :func:`glossrig.core.extraction.extract.block_status`). The samples table keeps
the block on its other channels (NaN in the missing one, :mod:`glossrig.core.samples`);
this module says what was lost, so that the capture can be repeated with the exposure
table it needed:

* per capture (sample, reference), rotation, LED and channel: how many of the lit blocks
  (blocks with at least one valid channel) miss the channel, why, where on the BRDF
  (quantiles of theta_h, theta_in, theta_out of those blocks) and the exposure that would
  have given them a value: for too-dark blocks the longest exposure scaled by the ratio of
  the noise floor to the channel's value there
  (:func:`glossrig.core.radiometry.hdr.exposure_to_fix`; the median and the 95th
  percentile over the blocks, the latter the longest exposure the table needs to recover
  95 % of them), for saturated ones the shortest exposure needed where the shortest
  exposure still saw a value below saturation;
* blocks with no valid channel at all (in shadow, beside the sample, or out of range in
  every channel), counted apart: their exposure is not a channel's problem;
* per channel, how many rows of the samples table miss it.

:func:`dynamic_range_report` builds the report (plain JSON), :func:`log_dynamic_range`
logs it (warnings for shortfalls of at least :data:`LOG_FRACTION` of an LED's lit blocks),
:func:`write_dynamic_range` writes ``dynamic_range.json`` and ``dynamic_range.png`` into
the extraction's plots folder.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd

from glossrig.core.radiometry import hdr as hdrmod

_log = logging.getLogger(__name__)

FORMAT = "glossrig-dynamic-range/1"
CHANNELS = ("r", "g", "b")
#: a shortfall is logged as a warning from this fraction of an LED's lit blocks on
LOG_FRACTION = 0.05
_REASON = {hdrmod.TOO_DARK: "too dark", hdrmod.TOO_BRIGHT: "saturated", hdrmod.TOO_FEW: "too few exposures"}
_ANGLES = ("theta_h", "theta_in", "theta_out")


def _num(v):
    """A JSON number, or None for NaN / infinity."""
    v = float(v)
    return v if math.isfinite(v) else None


def _region(sub: pd.DataFrame) -> dict:
    """5th, 50th and 95th percentiles (degrees) of the blocks' angles."""
    return {f"{a}_deg": [round(float(np.degrees(x)), 2) for x in np.percentile(sub[a].to_numpy(), [5, 50, 95])]
            for a in _ANGLES if a in sub and len(sub)}


def _shortfalls(table: pd.DataFrame, capture: str, exposures: list[float] | None) -> tuple[list, list]:
    """Per (rotation, LED, channel, reason) of one measured capture: the missing channel's
    blocks among the lit ones; and per (rotation, LED) the blocks without any channel."""
    out: list[dict] = []
    none: list[dict] = []
    if table is None or not len(table):
        return out, none
    t_min = min(exposures) if exposures else None
    t_max = max(exposures) if exposures else None
    vals = np.isfinite(table[list(CHANNELS)].to_numpy(np.float64))
    lit_all = vals.any(axis=1)
    for (rot, led), idx in table.groupby(["rotation", "led"], sort=True).indices.items():
        lit = lit_all[idx]
        n_lit = int(lit.sum())
        if n_lit < len(idx):
            entry = {"capture": capture, "rotation": float(rot), "led": int(led), "blocks": int(len(idx) - n_lit),
                     "fraction_of_blocks": round(float(1 - n_lit / len(idx)), 6)}
            dark_all = np.ones(len(idx) - n_lit, bool)
            for c in CHANNELS:
                if f"status_{c}" in table:
                    dark_all &= table[f"status_{c}"].to_numpy()[idx][~lit] == hdrmod.TOO_DARK
            entry["all_too_dark"] = int(dark_all.sum())
            none.append(entry)
        if n_lit == 0:
            continue
        sub = table.iloc[idx[lit]]
        for k, c in enumerate(CHANNELS):
            miss = ~vals[idx[lit], k]
            if not miss.any():
                continue
            st = (sub[f"status_{c}"].to_numpy() if f"status_{c}" in sub
                  else np.full(len(sub), hdrmod.TOO_FEW, np.uint8))
            fix = sub[f"fix_s_{c}"].to_numpy(np.float64) if f"fix_s_{c}" in sub else np.full(len(sub), np.nan)
            for code, reason in _REASON.items():
                m = miss & (st == code)
                if not m.any():
                    continue
                e = {"capture": capture, "channel": c, "rotation": float(rot), "led": int(led), "reason": reason,
                     "blocks": int(m.sum()), "fraction_of_lit_blocks": round(float(m.sum() / n_lit), 6),
                     **_region(sub[m])}
                f = fix[m]
                if code == hdrmod.TOO_DARK:
                    known = f[~np.isnan(f)]
                    e["longest_exposure_s"] = t_max
                    if known.size:
                        med, p95 = np.percentile(known, [50, 95])
                        e["exposure_to_fix_s"] = {"median": _num(med), "p95": _num(p95),
                                                  "no_signal": int(np.isinf(known).sum())}
                        if t_max and math.isfinite(p95):
                            e["longest_exposure_factor"] = round(float(p95 / t_max), 3)
                elif code == hdrmod.TOO_BRIGHT:
                    known = f[np.isfinite(f)]
                    e["shortest_exposure_s"] = t_min
                    e["exposure_to_fix_s"] = {"p5": _num(np.percentile(known, 5)) if known.size else None,
                                              "unknown_below_shortest": int(m.sum() - known.size)}
                out.append(e)
    return out, none


def dynamic_range_report(sample: pd.DataFrame, reference: pd.DataFrame | None, samples: pd.DataFrame,
                         exposures: dict | None = None) -> dict:
    """The report (module docstring) of an extraction: ``sample`` and ``reference`` the
    measured tables (:attr:`glossrig.core.extraction.extract.Measured.table`, with angles),
    ``samples`` the diffuse-normalised rows (:func:`glossrig.core.extraction.extract.diffuse_normalize`),
    ``exposures`` ``{"sample": [s, ...], "reference": [...]}`` the captures' exposure times."""
    exposures = exposures or {}
    short, none = [], []
    for name, table in (("sample", sample), ("reference", reference)):
        a, b = _shortfalls(table, name, exposures.get(name))
        short += a
        none += b
    short.sort(key=lambda e: (-e["fraction_of_lit_blocks"], e["capture"], e["channel"], e["rotation"], e["led"]))
    vals = np.isfinite(samples[list(CHANNELS)].to_numpy(np.float64)) if len(samples) else np.zeros((0, 3), bool)
    n = int(len(vals))
    table = {"rows": n, "rows_with_every_channel": int(vals.all(axis=1).sum()),
             "channels": {c: {"valid": int(vals[:, k].sum()), "missing": int(n - vals[:, k].sum()),
                              "fraction_missing": round(float(1 - vals[:, k].mean()), 6) if n else None}
                          for k, c in enumerate(CHANNELS)}}
    return {"format": FORMAT, "noise_floor": hdrmod.LO, "saturation_limit": hdrmod.HI,
            "exposures_s": {k: [min(v), max(v)] for k, v in exposures.items() if v},
            "samples_table": table, "channel_shortfalls": short, "blocks_without_any_channel": none,
            "definitions": {
                "fraction_of_lit_blocks": "blocks of that rotation and LED missing the channel, over the blocks with "
                                          "at least one valid channel in that capture",
                "exposure_to_fix_s": "too dark: the longest exposure scaled by the noise floor over the channel's "
                                     "value at it (median and 95th percentile over the blocks; p95 = the longest "
                                     "exposure that recovers 95 % of them; no_signal: blocks with no signal at all); "
                                     "saturated: the shortest exposure that keeps the value below the saturation "
                                     "limit, where the shortest exposure saw one (p5), else unknown",
                "angles": "5th, 50th and 95th percentiles, degrees, of the blocks missing the channel"}}


def merge_reports(parts: list[dict]) -> dict:
    """The report of a whole extraction from :func:`dynamic_range_report` of its parts (disjoint
    (rotation, LED) units of the sample and the reference, as
    :func:`glossrig.core.extraction.extract.extract_samples` streams them; the same exposures):
    equal to the report of the concatenated tables when ``parts`` come in that order (sample
    units by rotation and LED, then the reference's). Shortfalls are sorted as there, the
    samples table's counts summed."""
    if not parts:
        raise ValueError("merge_reports: no parts")
    out = dict(parts[0])
    short = [e for p in parts for e in p["channel_shortfalls"]]
    short.sort(key=lambda e: (-e["fraction_of_lit_blocks"], e["capture"], e["channel"], e["rotation"], e["led"]))
    n = sum(p["samples_table"]["rows"] for p in parts)
    chans = {}
    for c in CHANNELS:
        valid = sum(p["samples_table"]["channels"][c]["valid"] for p in parts)
        chans[c] = {"valid": valid, "missing": n - valid,
                    "fraction_missing": round(float(1 - valid / n), 6) if n else None}
    out["samples_table"] = {"rows": n, "rows_with_every_channel": sum(p["samples_table"]["rows_with_every_channel"]
                                                                      for p in parts), "channels": chans}
    out["channel_shortfalls"] = short
    out["blocks_without_any_channel"] = [e for p in parts for e in p["blocks_without_any_channel"]]
    return out


def shortfall_text(e: dict) -> str:
    """One line for a channel shortfall of :func:`dynamic_range_report`."""
    where = ", ".join(f"{k[:-4]} {v[0]:.0f}-{v[2]:.0f} deg" for k, v in e.items() if k.endswith("_deg"))
    text = (f"{e['capture']} channel {e['channel']} {e['reason']} in {100 * e['fraction_of_lit_blocks']:.1f} % "
            f"({e['blocks']}) of the lit blocks of LED {e['led']} at rotation {e['rotation']:g} deg ({where})")
    fix = e.get("exposure_to_fix_s") or {}
    if e["reason"] == "too dark" and fix.get("p95") is not None:
        text += (f"; a longest exposure of {fix['p95']:.3g} s (x{e.get('longest_exposure_factor', float('nan')):.3g} "
                 f"the {e['longest_exposure_s']:g} s) would give 95 % of them a value")
    elif e["reason"] == "too dark" and fix.get("no_signal"):
        text += "; no signal at all in the longest exposure"
    elif e["reason"] == "saturated":
        if fix.get("p5") is not None:
            text += f"; a shortest exposure of {fix['p5']:.3g} s would keep 95 % of those measured below saturation"
        if fix.get("unknown_below_shortest"):
            text += (f"; {fix['unknown_below_shortest']} saturated even at the shortest {e['shortest_exposure_s']:g} s "
                     f"(needed: shorter, unknown by how much)")
    return text


def log_dynamic_range(report: dict, log=None) -> None:
    """Log the report: per channel how many samples miss it (info), and every shortfall
    of at least :data:`LOG_FRACTION` of an LED's lit blocks (warning)."""
    info = log or _log.info
    warn = log or _log.warning
    t = report["samples_table"]
    miss = [f"{c} {100 * d['fraction_missing']:.1f} %" for c, d in t["channels"].items() if d["missing"]]
    if miss:
        info(f"extract: {t['rows']} samples, {t['rows'] - t['rows_with_every_channel']} of them kept on their valid "
             f"channels only (missing: {', '.join(miss)}; NaN in the table)")
    for e in report["channel_shortfalls"]:
        if e["fraction_of_lit_blocks"] >= LOG_FRACTION:
            warn(f"extract: {shortfall_text(e)}")


def write_dynamic_range(folder: Path, report: dict, samples: pd.DataFrame) -> None:
    """``dynamic_range.json`` (the report) and ``dynamic_range.png`` (per channel, the
    samples' coverage in theta_h / theta_d, missing ones marked) into ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from glossrig.core.atomic import atomic_write_bytes

    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(folder / "dynamic_range.json",
                       (json.dumps(report, indent=1, allow_nan=False) + "\n").encode())
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.3), sharey=True)
    s = samples.sample(min(len(samples), 20000), random_state=0) if len(samples) else samples
    for ax, c in zip(axes, CHANNELS):
        ok = np.isfinite(s[c].to_numpy(np.float64))
        th, td = np.degrees(s["theta_h"].to_numpy()), np.degrees(s["theta_d"].to_numpy())
        ax.scatter(th[ok], td[ok], s=1, c="0.7", label="valid")
        ax.scatter(th[~ok], td[~ok], s=2, c="tab:red", label="missing (out of dynamic range)")
        d = report["samples_table"]["channels"][c]
        ax.set(title=f"channel {c}: {100 * (d['fraction_missing'] or 0):.1f} % missing", xlabel="theta_h (deg)")
    axes[0].set_ylabel("theta_d (deg)")
    axes[0].legend(markerscale=6, fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "dynamic_range.png", dpi=110)
    plt.close(fig)
