"""Example measurement reports (issue #17): one twin and one real-material (RGL) measurement,
each with a headless-Chromium screenshot of its HTML report.

    nice -n 5 python -m validation.report_examples [--work DIR] [--out validation/report_examples]

* twin: ``glossrig demo --out WORK/twin --resume`` (sample_2_6, scale 0.25, the middle-row
  LEDs, rotation 0: checkerboard, transparency-sheet, lambert:0.8 reference and sample
  captures, then ``glossrig measure``). ``--seed-twin DIR`` copies an earlier demo folder
  to WORK/twin first (when WORK/twin does not exist) so that --resume reuses it.
* rgl: twin captures of a real measured BRDF (``measured:RGL/MATERIAL.bsdf``, default
  satin_rosaline_rgb) with the real white paper (``measured:RGL/paper_white_rgb.bsdf``) as
  the diffuse reference, as validation/diagnose/rgl_study.py measures them: scale 0.25,
  middle-row LEDs, rotation 0, one repeat, the thesis normalisation (Lambertian reference of
  albedo 0.8, the default of --reference-albedo). The camera and lamp calibrations are the
  twin run's (same rig, same scale). Then ``glossrig measure ... --resume``.

Captures are reused: a complete capture in WORK is not simulated again, an interrupted one
is finished with ``glossrig simulate --resume``, and ``glossrig measure --resume`` redoes
only the steps whose inputs changed. WORK defaults to a new temporary folder.

Into OUT/{twin,rgl}/ go report.html, report.md, report_figures/, fit.json (recovery.json on
the twin), camera.json, lamps.json, exports/ and screenshot.png (report.html in headless
Chromium). Never copied: samples.parquet, exports/samples.csv (tens of MB), plots/,
renders/ (their PNGs are in the report) and the capture folders (hundreds of MB). When the
whole of OUT would exceed --max-mb, PNGs of report_figures/ that report.html embeds byte
for byte are left out, largest first; OUT/README.md lists everything left out and why.
"""
from __future__ import annotations

import argparse
import base64
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from glossrig.core.fitting.export import read_fit_file
from glossrig.core.report.recovery import read_recovery
from validation.common import capture, glossrig
from validation.paths import ROOT, rgl_dir

SCALE = 0.25
REF_SEED, SAMPLE_SEED = 5, 6          # the twin demo uses seeds 1-4
ALWAYS_SKIP = {"samples.parquet", "samples.csv"}


def simulate(out: Path, material: str, seed: int) -> Path:
    """A middle-LED, rotation-0 capture at SCALE; reused when complete, finished when interrupted."""
    return capture(out, material, SCALE, seed, "0", 1, mode="resume", echo="+")


def twin(work: Path, seed_from: str | None) -> Path:
    d = work / "twin"
    if seed_from and not d.exists():
        print(f"seeding {d} from {seed_from}", flush=True)
        subprocess.run(["cp", "-a", seed_from, str(d)], check=True)
    glossrig("demo", "--out", d, "--scale", SCALE, "--resume", echo="+")
    return d


def rgl(work: Path, material: str, twin_dir: Path) -> Path:
    d = work / "rgl"
    d.mkdir(parents=True, exist_ok=True)
    rgl = rgl_dir()
    ref = simulate(d / "reference", f"measured:{rgl / 'paper_white_rgb.bsdf'}", REF_SEED)
    sample = simulate(d / "sample", f"measured:{rgl / (material + '.bsdf')}", SAMPLE_SEED)
    for name in ("camera.json", "lamps.json"):
        src, dst = twin_dir / name, d / name
        if not dst.exists() or dst.read_bytes() != src.read_bytes():
            shutil.copy(src, dst)
    m = d / "measure"
    glossrig("measure", sample, "--reference", ref, "--camera", d / "camera.json", "--lamps", d / "lamps.json",
             "--out", m, "--resume", "--no-progress", echo="+")
    return m


def screenshot(html: Path, png: Path, width: int, height: int) -> None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or "chromium"
    cmd = [chromium, "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
           f"--screenshot={png}", f"--window-size={width},{height}", html.resolve().as_uri()]
    print("+ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    if not png.exists():
        raise SystemExit(f"chromium wrote no screenshot {png}")
    # the whole page at half size in 256 colours: readable, and about a quarter of the bytes
    from PIL import Image

    with Image.open(png) as im:
        im = im.convert("RGB")
        rows = np.flatnonzero(np.asarray(im).min(axis=(1, 2)) < 250)        # drop the blank tail of the window
        if rows.size:
            im = im.crop((0, 0, im.width, min(im.height, int(rows[-1]) + 40)))
        im = im.resize((im.width // 2, im.height // 2), Image.Resampling.LANCZOS)
        im.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(png, optimize=True)


def collect(meas: Path, dest: Path, skipped: list) -> None:
    """Copy the report's outputs of one measurement folder into DEST (replacing it)."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    # report.md is left out: its figures (report_figures/) are the PNGs report.html embeds, and
    # committing both would double the size; the command writes all three
    for name in ("report.html", "fit.json", "recovery.json", "camera.json", "lamps.json"):
        src = meas / name if (meas / name).exists() else meas.parent / name   # rgl: calibrations beside measure/
        if src.exists():
            shutil.copy(src, dest / name)
    for sub in ("exports",):
        if not (meas / sub).is_dir():
            continue
        (dest / sub).mkdir()
        for f in sorted((meas / sub).iterdir()):
            if f.name in ALWAYS_SKIP:
                skipped.append((f"{dest.name}/{sub}/{f.name}", f.stat().st_size,
                                "too large to commit; made again by the command"))
            elif f.is_file():
                shutil.copy(f, dest / sub / f.name)
    for name in ("samples.parquet",):
        if (meas / name).exists():
            skipped.append((f"{dest.name}/{name}", (meas / name).stat().st_size,
                            "too large to commit; made again by the command"))


def size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def embedded_pngs(html: Path) -> set[bytes]:
    return {base64.b64decode(m) for m in re.findall(rb'data:image/png;base64,([A-Za-z0-9+/=]+)', html.read_bytes())}


def fit_budget(out: Path, max_bytes: int, skipped: list) -> None:
    """Leave out report_figures/ PNGs that report.html embeds byte for byte, largest first,
    until OUT fits MAX_BYTES."""
    cands = []
    for d in ("twin", "rgl"):
        html = out / d / "report.html"
        emb = embedded_pngs(html) if html.exists() else set()
        for f in (out / d / "report_figures").glob("*.png"):
            if f.read_bytes() in emb:
                cands.append(f)
    for f in sorted(cands, key=lambda f: -f.stat().st_size):
        if size(out) <= max_bytes:
            break
        skipped.append((str(f.relative_to(out)), f.stat().st_size,
                        "embedded byte for byte in report.html; left out for the size budget"))
        f.unlink()
    for d in ("twin", "rgl"):
        fig = out / d / "report_figures"
        if fig.is_dir() and not any(fig.iterdir()):
            fig.rmdir()


def _fmt(x, nd=4) -> str:
    return "-" if x is None else f"{x:.{nd}g}"


def readme(out: Path, a, timings: dict, skipped: list, material: str) -> None:
    L = ["# Example measurement reports (issue #17)", "",
         "Made by one command (captures reused from WORK when complete; WORK defaults to a temporary folder):", "",
         "    nice -n 5 python -m validation.report_examples --work WORK [--seed-twin EARLIER_DEMO_DIR]", "",
         "| folder | measurement |", "|---|---|",
         "| twin/ | `glossrig demo --out WORK/twin --resume`: the twin's sample_2_6 (an extended-Ward material with "
         "known parameters), scale 0.25, middle-row LEDs 5-12, rotation 0, lambert:0.8 reference; camera and lamps "
         "calibrated from simulated checkerboard and transparency-sheet captures |",
         f"| rgl/ | a real measured material on the twin: `measured:{material}.bsdf` (RGL database, Dupuy & Jakob "
         "2018) as the sample and the real white paper `measured:paper_white_rgb.bsdf` as the diffuse reference, "
         f"scale 0.25, LEDs 5-12, rotation 0, seeds {REF_SEED} (reference) and {SAMPLE_SEED} (sample), as "
         "validation/diagnose/rgl_study.py measures them; the twin run's camera.json and lamps.json (same rig and "
         "scale); `glossrig measure SAMPLE --reference REF --camera camera.json --lamps lamps.json` with the default "
         "thesis normalisation (Lambertian reference of albedo 0.8) |", "",
         "Each folder holds `report.html` (self-contained: every figure embedded), `screenshot.png` (that page in "
         f"headless Chromium, `--window-size={a.width},{a.height}`, the whole page, stored at half size in 256 "
         "colours), `fit.json`, `camera.json`, `lamps.json`, `exports/` (Mitsuba XML for the "
         "project's plugin and for stock plugins, BRDF Explorer `.brdf`, `samples.csv.json` describing the CSV) "
         "and `recovery.json` (the calibrations against the twin's truth; on twin/ also the material's Ward "
         "parameters, which rgl/ has none of). The report paths name the folders the measurement ran in (WORK). "
         "The command also writes `report.md` with its figures in `report_figures/` (the same PNGs report.html "
         "embeds); they are not committed, to halve the size.", ""]
    rec = out / "twin/recovery.json"
    if rec.exists():
        r = read_recovery(rec)
        mat = r["material"]
        L += ["## twin: recovery of the twin's truth (recovery.json)", "",
              f"Camera: fx {r['intrinsics']['fx_error_percent']:+.3f} %, fy {r['intrinsics']['fy_error_percent']:+.3f} %, "
              f"principal point ({r['intrinsics']['cx_error_px']:+.2f}, {r['intrinsics']['cy_error_px']:+.2f}) px. "
              f"Lamps: worst position error {r['lamps']['worst_error_mm']:.2f} mm over {r['lamps']['n_leds']} LEDs.", "",
              "| parameter | true | fitted (luminance) | error |", "|---|---|---|---|"]
        for k in ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"):
            e = mat["error"].get(f"{k}_percent")
            err = f"{e:+.2f} %" if e is not None else f"{mat['error']['lobe_rotation_deg']:.2f} deg"
            L.append(f"| {k} | {_fmt(mat['true'][k])} | {_fmt(mat['fitted'][k])} | {err} |")
        L.append("")
    fj = out / "rgl/fit.json"
    if fj.exists():
        L += [f"## rgl: fitted parameters of {material} (fit.json)", "",
              "The RGL material is a measured BRDF, not an extended-Ward material: there are no true Ward "
              "parameters to compare with, only the best Ward fit the rig's angles (theta_d up to ~27 deg) "
              "support. Its absolute scale also carries the thesis assumption that the paper is Lambertian "
              "of albedo 0.8 (validation/diagnose/rgl_study.md measures both effects against the measured "
              "BRDF itself). Standard errors are noise-only.", "",
              "| channel | rho_d | rho_s | alpha_x | alpha_y | lobe_rotation (rad) | RMS relative residual |",
              "|---|---|---|---|---|---|---|"]
        f = read_fit_file(fj)
        for ch, wf in f.fit.fits.items():
            c = wf.to_json()
            L.append(f"| {ch} | " + " | ".join(_pm(c, k) for k in ("rho_d", "rho_s", "alpha_x", "alpha_y",
                                                                   "lobe_rotation")) +
                     f" | {_fmt(_find(c, ('rms_relative',)), 3)} |")
        g = f.gloss
        if g:
            L += ["", "Gloss of the fitted luminance model (fit.json): " +
                  ", ".join(f"{k} {_fmt(g.get(k), 3)}" for k in ("gu20", "gu60", "gu85", "haze", "doi") if k in g) +
                  " (60 and 85 deg gloss, haze and DOI are extrapolations beyond the rig's angles, see the report).", ""]
    L += ["## Run time", "",
          "From scratch on the 2-core development machine (nice -n 5): the twin demo about 10 min (four captures "
          "and glossrig measure), the two RGL captures 2.4 and 1.3 min, the RGL glossrig measure 1.7 min "
          "(extract 42 s, report 37 s), the screenshots a few seconds each. With every capture and step "
          "complete in WORK a rerun takes about 10 s. This run (steps reused where WORK held them):", ""]
    L += [f"* {k}: {v:.0f} s" for k, v in timings.items()]
    L += ["", f"Committed size: {size(out) / 1e6:.1f} MB (budget --max-mb {a.max_mb:g}).", ""]
    if skipped:
        L += ["## Left out", "", "| file | size | why |", "|---|---|---|"]
        L += [f"| {p} | {s / 1e6:.1f} MB | {why} |" for p, s, why in skipped]
        L += ["", "Also never copied: the capture folders (about 420 MB each), plots/ and renders/ (their "
              "images are in the reports).", ""]
    (out / "README.md").write_text("\n".join(L))


def _find(c: dict, keys):
    r = c.get("residuals", {})
    for k in keys:
        if k in r:
            return r[k]
    return None


def _pm(c: dict, k: str) -> str:
    v, s = c.get(k), c.get(f"{k}_stderr")
    return _fmt(v) + (f" +- {s:.2g}" if isinstance(s, (int, float)) else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="folder for captures and measurements (default: a new temp folder)")
    ap.add_argument("--out", default=str(ROOT / "validation/report_examples"))
    ap.add_argument("--material", default="satin_rosaline_rgb", help="RGL material (a .bsdf in SHARED/data/rgl, validation.paths)")
    ap.add_argument("--seed-twin", default=None, help="copy this earlier `glossrig demo` folder to WORK/twin "
                    "first (when WORK/twin does not exist), so that --resume reuses its steps")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=16000)
    ap.add_argument("--max-mb", type=float, default=10.0)
    a = ap.parse_args(argv)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="report_examples_"))
    work.mkdir(parents=True, exist_ok=True)
    out = Path(a.out)
    print(f"work folder: {work}", flush=True)
    timings, skipped = {}, []
    t0 = time.time()
    tw = twin(work, a.seed_twin)
    timings["twin (glossrig demo --resume)"] = time.time() - t0
    t1 = time.time()
    rm = rgl(work, a.material, tw)
    timings["rgl (2 captures + glossrig measure --resume)"] = time.time() - t1
    out.mkdir(parents=True, exist_ok=True)
    t2 = time.time()
    for name, meas in (("twin", tw), ("rgl", rm)):
        collect(meas, out / name, skipped)
        screenshot(out / name / "report.html", out / name / "screenshot.png", a.width, a.height)
    fit_budget(out, int(a.max_mb * 1e6), skipped)
    timings["copy + screenshots"] = time.time() - t2
    timings["total"] = time.time() - t0
    readme(out, a, timings, skipped, a.material)
    print(f"wrote {out} ({size(out) / 1e6:.1f} MB); work folder {work}", flush=True)


if __name__ == "__main__":
    from validation.common import run_main

    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(run_main(main))
