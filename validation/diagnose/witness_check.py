"""What diagnose's witnesses outside the BRDF rows measured over a blind study's captures (issue 14):
the sample radius on the cylinder's outline (core/diagnose/silhouette.py) and the LED moves on the
marker band (core/diagnose/marker_band.py) - the hidden size against the witness's, and what each
says on every capture that hides no such effect.

    python -m validation.diagnose.witness_check WORK [WORK ...] [--out FILE.md [--force]]

WORK: a blind study's work folder (validation.diagnose.blind_study) whose trials and independent
nulls have been diagnosed; each report.json's ``meta.sample_radius_silhouette`` and
``meta.led_position_band`` are read, nothing is measured again. Written: Markdown (stdout, or --out).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

#: witness -> (report.json meta key, the cause it measures, its estimate's key, unit)
WITNESSES = {"outline": ("sample_radius_silhouette", "sample_radius_error", "dr", "mm"),
             "marker band": ("led_position_band", "led_position_error", "magnitude", "mm RMS per axis")}


def records(work: Path) -> list[dict]:
    """One row per diagnosed capture of WORK: its name, material, hidden causes (with their true sizes)
    and, per witness, its estimate, standard error, significance and why not; a capture without a
    report is left out."""
    trials = json.loads((work / "trials.json").read_text())
    nulls = json.loads((work / "nulls.json").read_text()) if (work / "nulls.json").exists() else []
    out = []
    for name, rec in [(f"t{t['trial']:03d}", t) for t in trials] + [(f"n{n['null']:02d}", n) for n in nulls]:
        rep = work / f"{name}_report" / "report.json"
        if not rep.exists():
            continue
        r = json.loads(rep.read_text())
        row = {"capture": name, "material": rec["material"], "hidden": rec.get("hidden", {}),
               "code": rec.get("code", {}).get("diagnose"),
               "true": rec.get("true_magnitude", {}), "verdict": r["verdict"], "ranking": r.get("ranking", [])}
        for w, (key, cause, est, _) in WITNESSES.items():
            ev = r.get("meta", {}).get(key)
            c = next((x for x in r["causes"] if x["name"] == cause), {})
            row[w] = None if ev is None else {"value": ev.get(est), "se": ev.get("se"), "significant": ev["significant"],
                                              "why_not": ev.get("why_not"), "refuted": bool(c.get("refuted"))}
        out.append(row)
    return out


def title(work: Path, rows: list[dict]) -> str:
    """The study's LEDs (:func:`validation.diagnose.blind_study.study_leds`) and the code its
    diagnoses ran with (the commits the diagnosed captures' records name)."""
    from validation.diagnose.blind_study import study_leds

    leds = study_leds(work) or ()
    ran = sorted({(c or {}).get("commit", "?") + ("+dirty" if (c or {}).get("dirty") else "")
                  for c in (r["code"] for r in rows)})
    return (f"## The blind study of {len(leds)} LEDs ({', '.join(map(str, leds))}; WORK `{work.name}`, "
            f"diagnoses at {', '.join(ran)})")


def summary(work: Path, rows: list[dict]) -> str:
    L = [title(work, rows), ""]
    for w, (_, cause, _, unit) in WITNESSES.items():
        have = [r for r in rows if r[w] is not None]
        hid = [r for r in have if cause in r["hidden"]]
        free = [r for r in have if cause not in r["hidden"]]
        read = [r for r in free if np.isfinite(r[w]["value"] if r[w]["value"] is not None else np.nan)]
        L += [f"### {w} ({cause}, {unit})", "",
              f"captures hiding no {cause}: {len(free)}; a signature named in {sum(r[w]['significant'] for r in free)}; "
              f"read (not stopped by an effect that bends it) in {len(read)}"
              + (f", |estimate| / se there: median {np.median([abs(r[w]['value']) / r[w]['se'] for r in read]):.2f}, "
                 f"largest {max(abs(r[w]['value']) / r[w]['se'] for r in read):.2f}" if read else "")
              + f"; the BRDF-space cause refuted by it in {sum(r[w]['refuted'] for r in free)}", ""]
        if hid:
            L += ["| capture | material | hidden | true | witness | se | signature | verdict | first two |",
                  "|---|---|---|---|---|---|---|---|---|"]
            for r in hid:
                e = r[w]
                L.append(f"| {r['capture']} | {r['material']} | {' + '.join(r['hidden'])} | {r['true'][cause]:+.3f} | "
                         f"{e['value']:+.3f} | {e['se']:.3f} | {'yes' if e['significant'] else 'no: ' + str(e['why_not'])} | "
                         f"{r['verdict']} | {', '.join(r['ranking'][:2])} |")
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
    text = ("# diagnose's witnesses over the blind studies' captures\n\n"
            "Regenerate: `python -m validation.diagnose.witness_check WORK [WORK ...] --out FILE --force` on the blind "
            "studies' work folders after their runs (it reads each report.json; nothing is measured again).\n\n"
            + "\n".join(summary(w, records(w)) for w in a.work))
    if a.out:
        a.out.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
