"""The sample radius read on the cylinder's outline (core/diagnose/silhouette.py) over a blind
study's captures: the hidden radius against the outline's, and what the outline says on every
capture that hides none (issue 14).

    python -m validation.diagnose.silhouette_check WORK [WORK ...] [--out FILE.md [--force]]

WORK: a blind study's work folder (validation.diagnose.blind_study) whose trials and independent
nulls have been diagnosed; each report.json's ``meta.sample_radius_silhouette`` is read, nothing is
measured again. Written: a Markdown table per folder (to stdout, or --out).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def records(work: Path) -> list[dict]:
    """One row per diagnosed capture of WORK: its name, material, hidden causes (with the radius's
    true size) and the outline's estimate; a capture whose report lacks the estimate is left out."""
    trials = json.loads((work / "trials.json").read_text())
    nulls = json.loads((work / "nulls.json").read_text()) if (work / "nulls.json").exists() else []
    out = []
    for name, rec in [(f"t{t['trial']:03d}", t) for t in trials] + [(f"n{n['null']:02d}", n) for n in nulls]:
        rep = work / f"{name}_report" / "report.json"
        if not rep.exists():
            continue
        r = json.loads(rep.read_text())
        ev = r.get("meta", {}).get("sample_radius_silhouette")
        if ev is None:
            continue
        c = next((x for x in r["causes"] if x["name"] == "sample_radius_error"), {})
        out.append({"capture": name, "material": rec["material"], "hidden": rec.get("hidden", {}),
                    "true": rec.get("true_magnitude", {}).get("sample_radius_error"), "dr": ev["dr"], "se": ev["se"],
                    "significant": ev["significant"], "why_not": ev.get("why_not"),
                    "limbs": len(ev.get("limbs", [])), "verdict": r["verdict"],
                    "refuted": bool(c.get("refuted")), "named_by_outline": c.get("params", {}).get("fixed_by") == "silhouette"
                    or c.get("params", {}).get("confirmed_by") == "silhouette"})
    return out


def summary(work: Path, rows: list[dict]) -> str:
    hid = [r for r in rows if r["true"] is not None]
    free = [r for r in rows if r["true"] is None]
    L = [f"## {work}", ""]
    if free:
        z = np.array([abs(r["dr"]) / r["se"] for r in free])
        L += [f"captures hiding no radius error: {len(free)}; named significant by the outline: "
              f"{sum(r['significant'] for r in free)}; |dr| / se median {np.median(z):.2f}, largest {z.max():.2f} "
              f"(significance needs 4); |dr| largest {max(abs(r['dr']) for r in free):.3f} mm; "
              f"a BRDF-space radius refuted by the outline in {sum(r['refuted'] for r in free)}", ""]
    if hid:
        L += ["| capture | material | hidden | true dr (mm) | outline dr (mm) | se | (dr - true) / se | verdict |",
              "|---|---|---|---|---|---|---|---|"]
        for r in hid:
            L.append(f"| {r['capture']} | {r['material']} | {' + '.join(r['hidden'])} | {r['true']:+.3f} | "
                     f"{r['dr']:+.3f} | {r['se']:.3f} | {(r['dr'] - r['true']) / r['se']:+.2f} | {r['verdict']} |")
        L.append("")
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", nargs="+", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--force", action="store_true", help="overwrite --out")
    a = ap.parse_args(argv)
    if a.out and a.out.exists() and not a.force:
        ap.exit(2, f"{a.out} exists: give --force to overwrite it\n")
    for w in a.work:
        if not (w / "trials.json").exists():
            ap.exit(2, f"{w}: no trials.json (not a blind study's work folder)\n")
    text = "# The sample radius on the outline, over the blind studies' captures\n\n" + "\n".join(
        summary(w, records(w)) for w in a.work)
    if a.out:
        a.out.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
