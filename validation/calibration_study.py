"""Geometric calibration on the twin (thesis 4.3.2): measured figures for
validation/calibration_report.md.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
    .venv/bin/python -m validation.calibration_study --work /tmp/calstudy [--seeds 3] [--scale 0.25]

1. Intrinsics: ``glossrig simulate --target checkerboard --views 12 --scale S --seed s``
   then ``glossrig calibrate camera`` for seeds 1..N, and seed N with 30 views (as
   the thesis took); errors against truth.json.
2. Poses: ``glossrig simulate --material lambert:0.8 --leds 9 --rotations 0 --scale S
   --seed s`` (s = 2, 3, ... ) then the geometry step with the twin's true
   intrinsics (the pose step alone) and with the calibrated ones (seed-1
   checkerboard; the chain a user runs). Corner PnP (thesis method, 8 + 12
   points) and the raw-edge refinement, holder edges "inner" and "all".
3. Why targets are missed:
   a. sensitivity: how far (px) the holder-marker corners move for a 0.05 deg tilt;
   b. per-edge offsets of the twin image at the TRUE pose (each edge's best
      shift with the pose held at truth) against their noise;
   c. a synthetic holder-marker image rendered here exactly (supersampled
      geometry, Gaussian blur, pixel integration, Bayer, shot noise) - the
      estimator's own accuracy when the image matches its model;
   d. the holder marker imaged through the twin's own lens map without Monte
      Carlo (glossrig.twin.marker_image: exact fine-pixel coverage) with a 2x and
      the default 4x canvas, noise-free and with 6 sensor-noise draws: what the
      canvas discretisation and the sensor noise alone leave of the holder tilt.
Writes WORK/calibration_results.json and prints a markdown summary.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from glossrig.core.capture import load_manifest, read_truth
from validation.common import checkerboard, glossrig, simulate, truth_camera
from validation.paths import RIG


def rot_err(Ra, Rb) -> float:
    from glossrig.core.calibration.poses import rotation_angle_deg

    return rotation_angle_deg(np.asarray(Ra), np.asarray(Rb))


def tilt_axes_deg(R_est, R_true) -> list[float]:
    """Rotation error as a vector about the holder axes (deg)."""
    return np.degrees(cv2.Rodrigues(np.asarray(R_true).T @ np.asarray(R_est))[0].ravel()).tolist()


# ---------------------------------------------------------------- part 1

def intrinsics_part(work: Path, scale: float, runs: list[tuple[int, int]]) -> list[dict]:
    """``runs``: (seed, views) pairs."""
    from glossrig.core.calibration.intrinsics import load_camera

    rows = []
    for s, views in runs:
        tag = f"s{s}" if views == 12 else f"s{s}_v{views}"
        d = checkerboard(work / f"checker_{tag}", views, scale, s, stdout=False)
        cam = work / f"camera_{tag}.json"
        t0 = time.time()
        glossrig("calibrate", "camera", d, "--out", cam, "--force", "--no-progress", stdout=False)
        dt = time.time() - t0
        c = load_camera(cam)
        t = read_truth(d)
        K = np.array(t["camera_matrix"])
        rows.append({"seed": s, "views_shot": views, "views": len(c.meta["views"]),
                     "skipped": [x["file"] + ": " + x["reason"] for x in c.meta["skipped"]],
                     "fx_err_pct": 100 * (c.fx / K[0, 0] - 1), "fy_err_pct": 100 * (c.fy / K[1, 1] - 1),
                     "cx_err_px": c.cx - K[0, 2], "cy_err_px": c.cy - K[1, 2], "rms_px": c.rms_px,
                     "std": c.meta["std"], "seconds": dt, "camera_json": str(cam)})
    return rows


# ---------------------------------------------------------------- part 2

def pose_errors(res: dict, t: dict) -> dict:
    Rh, th = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    Rci, tci = np.array(t["cylinder_R_in_holder"]), np.array(t["cylinder_t_mm"])
    Rc, tc = Rh @ Rci, Rh @ tci + th
    out = {}
    for tag, h, c in (("corner_pnp", res["holder"]["corner_pnp"], res["cylinder"]["corner_pnp"]),
                      ("edge_refined", res["holder"], res["cylinder"])):
        from glossrig.core.calibration.poses import relative_to_holder

        Rr, tr = relative_to_holder(h["R"], h["t_mm"], c["R"], c["t_mm"])
        out[tag] = {
            "holder_rot_deg": rot_err(h["R"], Rh), "holder_rot_axes_deg": tilt_axes_deg(h["R"], Rh),
            "holder_t_mm": (np.asarray(h["t_mm"]) - th).tolist(),
            "cylinder_cam_rot_deg": rot_err(c["R"], Rc), "cylinder_cam_t_mm": (np.asarray(c["t_mm"]) - tc).tolist(),
            "cyl_in_holder_rot_deg": rot_err(Rr, Rci), "cyl_in_holder_t_mm": (tr - tci).tolist(),
        }
    if "edge_fit" in res["holder"]:
        out["noise_std"] = {"holder_rot_deg": res["holder"]["edge_fit"]["std_rot_deg"],
                            "holder_t_mm": res["holder"]["edge_fit"]["std_t_mm"],
                            "cylinder_rot_deg": res["cylinder"]["edge_fit"]["std_rot_deg"],
                            "cylinder_t_mm": res["cylinder"]["edge_fit"]["std_t_mm"]}
    return out


def poses_part(work: Path, scale: float, seeds: list[int], calibrated_camera: Path) -> list[dict]:
    from glossrig.core.calibration.poses import calibrate_capture

    rows = []
    for s in seeds:
        cap = simulate(work / f"cap_s{s}", "--material", "lambert:0.8", "--leds", 9, "--rotations", 0,
                       "--scale", scale, "--seed", s, stdout=False)
        t = read_truth(cap)
        row = {"seed": s}
        true_cam = truth_camera(cap, work / f"true_camera_{cap.name}.json")
        for cam_tag, cam in (("true_intrinsics", true_cam), ("calibrated_intrinsics", calibrated_camera)):
            for edges in ("inner", "all"):
                if cam_tag == "calibrated_intrinsics" and edges == "all":
                    continue
                t0 = time.time()
                diag = work / f"geometry_s{s}.png" if (cam_tag, edges) == ("true_intrinsics", "inner") else None
                res = calibrate_capture(cap, cam, holder_edge_set=edges, diagnostic=diag)
                row[f"{cam_tag}/{edges}"] = dict(pose_errors(res, t), seconds=time.time() - t0)
        rows.append(row)
    return rows


# ---------------------------------------------------------------- part 3

def sensitivity(rig, t: dict) -> dict:
    """Largest image displacement of the holder-marker corners (outer, inner) when
    the holder turns by 0.05 deg about its x or y axis through the marker centre."""
    from glossrig.core.calibration.markers import holder_marker_corners

    R, tt = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    K, d = np.array(t["camera_matrix"]), np.array(t["distortion"])
    out = {}
    for name, inner in (("outer", False), ("inner", True)):
        P = holder_marker_corners(rig, inner=inner)
        c = P.mean(axis=0)
        base, _ = cv2.projectPoints(P, cv2.Rodrigues(R)[0], tt, K, d)
        for ax in ("x", "y"):
            v = np.zeros(3)
            v["xy".index(ax)] = np.radians(0.05)
            dR = cv2.Rodrigues(v)[0]
            P2 = (P - c) @ dR.T + c
            moved, _ = cv2.projectPoints(P2, cv2.Rodrigues(R)[0], tt, K, d)
            out[f"{name}_tilt_{ax}_px"] = float(np.abs(moved - base).reshape(-1, 2).max())
    return out


def edge_offsets_at_truth(capture: Path, rig) -> dict:
    """Each marker edge's best shift (px, with its noise std) when the pose is
    held at the truth: how far the twin's image departs from the model."""
    from scipy.optimize import least_squares

    from glossrig.core.calibration import poses as P
    from glossrig.core.calibration.demosaic import channel_index
    from glossrig.core.calibration.marker_detect import _distort
    from glossrig.core.calibration.raw import linearize, read_raw

    t = read_truth(capture)
    K, dist = np.array(t["camera_matrix"]), np.array(t["distortion"])
    R, tt = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    fr = read_raw(capture / load_manifest(capture).select("calibration")[0].file)
    lin = linearize(fr)
    cid = channel_index(lin.shape, fr.cfa)
    from glossrig.core.calibration.markers import cylinder_marker_corners, holder_marker_corners

    def px(a, b):
        p = P._project_ideal(np.array([a, b]), R, tt, K)
        return float(np.linalg.norm(p[1] - p[0]))

    ho, hi = holder_marker_corners(rig), holder_marker_corners(rig, inner=True)
    cc = cylinder_marker_corners(rig)
    half_h = float(np.clip(0.4 * px(ho[0], hi[0]) / np.sqrt(2), 2.5, 15))     # as marker_poses
    half_c = float(np.clip(0.25 * px(cc[2], cc[3]), 2.5, 15))
    out = {"half_px": {"holder": half_h, "cylinder": half_c}}
    for name, edges, half in (("holder", P.holder_edges(rig), half_h),
                              ("cylinder", P.cylinder_edges(rig), half_c)):
        offs = []
        for E in edges:
            ideal = P._project_ideal(E, R, tt, K)
            q, v, c, seg, u = P._collect_side(lin, cid, K, dist, _distort(ideal, K, dist), ideal, half,
                                             3 + 0.3 * half)
            A = ideal[seg]
            e = ideal[seg + 1] - A
            e /= np.linalg.norm(e, axis=1, keepdims=True)
            n = np.stack([-e[:, 1], e[:, 0]], -1)
            d0 = np.sum((q - A) * n, axis=1)
            an = np.abs(n)
            groups = [np.flatnonzero(c == ch) for ch in range(3) if (c == ch).sum() >= 8]

            def res(x, w=None, *, d0=d0, an=an, groups=groups, u=u, v=v):
                phi = P.edge_profile(d0 - x[0], P.SIGMA_MIN + np.exp(x[1]), an.max(1), an.min(1))
                r = []
                for k, g in enumerate(groups):
                    X = np.stack([np.ones(len(g)), u[g], phi[g], u[g] * phi[g]], -1)
                    b, *_ = np.linalg.lstsq(X, v[g], rcond=None)
                    r.append((v[g] - X @ b) * (1 if w is None else w[k]))
                return np.concatenate(r)

            s0 = least_squares(res, [0.0, np.log(0.5)])
            r0 = res(s0.x)
            w, i = [], 0
            for g in groups:
                w.append(1 / np.sqrt(np.mean(r0[i:i + len(g)] ** 2)))
                i += len(g)
            s = least_squares(res, s0.x, args=(w,))
            J = s.jac
            s2 = s.fun @ s.fun / (len(s.fun) - 2)
            # pinv: on a sharp edge the blur can sit at its floor, where its column of J vanishes
            std = float(np.sqrt(np.linalg.pinv(J.T @ J)[0, 0] * s2))
            offs.append({"offset_px": float(s.x[0]), "std_px": std})
        out[name] = offs
    return out


def synthetic_holder(rig, t: dict, seed: int = 0, blur: float = 0.4, ss: int = 4, jitter: bool = True) -> dict:
    """Render the holder marker exactly (supersampled geometry through the lens
    model, Gaussian blur, pixel-area integration, RGGB sampling, shot + read
    noise at the twin calibration image's levels) and refine the holder pose
    from a start 0.5 deg / 0.5 mm off. Returns the errors per edge set.

    ``jitter=False`` samples each pixel on a regular ss x ss sub-grid, which
    quantises edges that run along pixel rows/columns to 1/ss px - a stand-in
    for any renderer whose pixel response depends on the sub-pixel phase (the
    twin's former single bilinear lens read was one; twin/render.py)."""
    from glossrig.core.calibration import poses as P
    from glossrig.core.calibration.markers import holder_marker_corners

    K, dist = np.array(t["camera_matrix"]), np.array(t["distortion"])
    R, tt = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    w, h = t["image_size"]
    outer, inner = holder_marker_corners(rig), holder_marker_corners(rig, inner=True)
    proj, _ = cv2.projectPoints(outer, cv2.Rodrigues(R)[0], tt, K, dist)
    proj = proj.reshape(-1, 2)
    x0, y0 = (np.floor(proj.min(0)) - 40).astype(int)
    x1, y1 = (np.ceil(proj.max(0)) + 40).astype(int)
    # supersampled pixel grid, stratified and jittered (pixel centres at integers): a regular
    # sub-grid would quantise edges aligned with the pixel rows to 1/ss px, a bias of its own
    rng = np.random.default_rng(seed)
    sub = np.arange(ss) / ss - 0.5
    xs = (np.arange(x0, x1)[:, None] + sub[None]).ravel()
    ys = (np.arange(y0, y1)[:, None] + sub[None]).ravel()
    X, Y = np.meshgrid(xs, ys)
    if jitter:
        X = X + rng.uniform(0, 1 / ss, X.shape)
        Y = Y + rng.uniform(0, 1 / ss, Y.shape)
    else:
        X, Y = X + 0.5 / ss, Y + 0.5 / ss
    pts = np.stack([X.ravel(), Y.ravel()], -1).reshape(-1, 1, 2)
    nrm = cv2.undistortPoints(pts, K, dist, R=np.eye(3), P=np.eye(3),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    rays = np.c_[nrm, np.ones(len(nrm))] @ R            # camera -> holder directions
    C = -R.T @ tt
    z = outer[0, 2]
    s = (z - C[2]) / rays[:, 2]
    hit = C[None, :2] + s[:, None] * rays[:, :2]
    inside = lambda q, sq: ((q[:, 0] > sq[:, 0].min()) & (q[:, 0] < sq[:, 0].max()) &
                            (q[:, 1] > sq[:, 1].min()) & (q[:, 1] < sq[:, 1].max()))
    red, white = np.array([0.27, 0.027, 0.025]), np.array([0.38, 0.55, 0.48])
    dark = np.array([0.015, 0.022, 0.019])
    img = np.where(inside(hit, inner)[:, None], white, np.where(inside(hit, outer)[:, None], red, dark))
    img = img.reshape(len(ys), len(xs), 3).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), blur * ss)
    img = img.reshape(y1 - y0, ss, x1 - x0, ss, 3).mean(axis=(1, 3))
    lin = np.zeros((h, w), np.float32)
    cfa = np.array([[0, 1], [1, 2]])
    yy, xx = np.mgrid[y0:y1, x0:x1]
    lin[y0:y1, x0:x1] = img[np.arange(y1 - y0)[:, None], np.arange(x1 - x0)[None], cfa[yy % 2, xx % 2]]
    e_per_unit = 15520 * 2.2 / 3.2          # electrons at white level, ISO 320 (the twin's sensor figures)
    lin = (rng.poisson(np.clip(lin, 0, None) * e_per_unit) + rng.normal(0, 3.0, lin.shape)) / e_per_unit
    lin = lin.astype(np.float32)
    dR = cv2.Rodrigues(np.radians([0.35, -0.35, 0.1]))[0]
    R0, t0 = R @ dR, tt + np.array([0.3, -0.3, 0.3])
    out = {}
    for name, sl in (("inner", slice(4, 8)), ("all", slice(0, 8))):
        edges = P.holder_edges(rig)[sl]
        fit = P.refine_pose_edges(lin, cfa, K, dist, R0, t0, edges, [12.0] * len(edges))
        out[name] = {"rot_deg": rot_err(fit["R"], R), "rot_axes_deg": tilt_axes_deg(fit["R"], R),
                     "t_mm": (fit["t"] - tt).tolist(), "std_rot_deg": fit["std_rot_deg"]}
    return out


def lens_map_holder(rig, scale: float, draws: int = 6) -> dict:
    """Part 3d: holder tilt (deg) refined from the true pose on the exact marker image
    through the twin's lens map, per canvas supersampling: noise-free and per noise draw."""
    from glossrig.core.calibration import poses as P
    from glossrig.twin.marker_image import holder_marker_mosaic
    from glossrig.twin.render import LensMap

    from glossrig.core.calibration.markers import holder_marker_corners

    R, t = rig.camera.pose()
    out = {}
    K = LensMap.build(rig.camera, scale, supersample=1).K
    p = P._project_ideal(np.array([holder_marker_corners(rig)[0], holder_marker_corners(rig, inner=True)[0]]), R, t, K)
    half = float(np.clip(0.4 * np.linalg.norm(p[1] - p[0]) / np.sqrt(2), 2.5, 15))       # as marker_poses
    for ss in (2, 4):
        lens = LensMap.build(rig.camera, scale, supersample=ss)
        rows = []
        for k in range(draws + 1):
            lin = holder_marker_mosaic(rig, lens, R, t, None if k == 0 else np.random.default_rng(k))
            fit = P.refine_pose_edges(lin, rig.camera.cfa, lens.K, lens.dist, R, t, P.holder_edges(rig)[4:],
                                      [half] * 4)
            rows.append({"rot_deg": rot_err(fit["R"], R), "rot_axes_deg": tilt_axes_deg(fit["R"], R),
                         "std_rot_deg": fit["std_rot_deg"]})
        out[f"s{ss}"] = {"noise_free": rows[0], "noisy": rows[1:]}
    return out


# ------------------------------------------------------------------ main

def fmt(v, nd=3):
    return f"{v:.{nd}f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="folder for the simulated captures and results")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--seeds", type=int, default=3,
                    help="captures per part (checkerboard seeds 1.. with 12 views plus the last seed with 30; "
                         "sample seeds 2..)")
    a = ap.parse_args()
    from glossrig.core.rig import load_rig

    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rig = load_rig(RIG)
    results = {"scale": a.scale}
    runs = [(s, 12) for s in range(1, a.seeds + 1)] + [(a.seeds, 30)]        # the thesis took 30 views
    results["intrinsics"] = intr = intrinsics_part(work, a.scale, runs)
    results["poses"] = poses = poses_part(work, a.scale, list(range(2, a.seeds + 2)), Path(intr[0]["camera_json"]))
    cap = work / "cap_s2"
    t = read_truth(cap)
    results["sensitivity_0p05deg"] = sensitivity(rig, t)
    results["edge_offsets_at_truth"] = edge_offsets_at_truth(cap, rig)
    results["synthetic_holder"] = [synthetic_holder(rig, t, seed=k) for k in range(3)]
    results["synthetic_holder_regular_subgrid"] = [synthetic_holder(rig, t, seed=k, jitter=False) for k in range(3)]
    results["lens_map_holder"] = lens_map_holder(rig, a.scale)
    results["twin_supersample"] = t.get("supersample")
    (work / "calibration_results.json").write_text(json.dumps(results, indent=1))

    # ---- markdown summary
    print(f"## Intrinsics (scale {a.scale})\n")
    print("| seed | views shot / used | fx err % | fy err % | cx err px | cy err px | sd cx, cy px | RMS px | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in intr:
        print(f"| {r['seed']} | {r['views_shot']} / {r['views']} | {r['fx_err_pct']:+.3f} | {r['fy_err_pct']:+.3f} | {r['cx_err_px']:+.2f} | "
              f"{r['cy_err_px']:+.2f} | {r['std']['cx']:.1f}, {r['std']['cy']:.1f} | {r['rms_px']:.3f} | {r['seconds']:.1f} |")
    print(f"\n## Poses (scale {a.scale})\n")
    print("| seed | intrinsics / holder edges | method | holder rot deg | holder |dt| mm | cyl (camera) rot deg | "
          "cyl in holder rot deg | cyl in holder dt mm (x, y, z) | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in poses:
        for key, v in r.items():
            if key == "seed":
                continue
            for m in ("corner_pnp", "edge_refined"):
                e = v[m]
                print(f"| {r['seed']} | {key} | {m} | {fmt(e['holder_rot_deg'])} | {fmt(np.linalg.norm(e['holder_t_mm']))} | "
                      f"{fmt(e['cylinder_cam_rot_deg'])} | {fmt(e['cyl_in_holder_rot_deg'])} | "
                      f"{', '.join(f'{x:+.3f}' for x in e['cyl_in_holder_t_mm'])} | {v['seconds']:.1f} |")
    print("\nnoise-only standard deviations reported by the edge fit (true intrinsics, inner), per seed:")
    for r in poses:
        ns = r["true_intrinsics/inner"]["noise_std"]
        print(f"  seed {r['seed']}: holder rot (x, y, z) deg {[round(x, 3) for x in ns['holder_rot_deg']]}, "
              f"t mm {[round(x, 3) for x in ns['holder_t_mm']]}; cylinder rot deg "
              f"{[round(x, 3) for x in ns['cylinder_rot_deg']]}, t mm {[round(x, 3) for x in ns['cylinder_t_mm']]}")
    print("\n## Why\n")
    print("sensitivity (px moved by a 0.05 deg tilt):", json.dumps({k: round(v, 4) for k, v in
                                                                  results["sensitivity_0p05deg"].items()}))
    for k in ("holder", "cylinder"):
        o = results["edge_offsets_at_truth"][k]
        print(f"{k} edge offsets at the true pose (px): " +
              ", ".join(f"{x['offset_px']:+.3f}+-{x['std_px']:.3f}" for x in o))
    for key in ("synthetic_holder", "synthetic_holder_regular_subgrid"):
        for k, s in enumerate(results[key]):
            print(f"{key} (seed {k}): rot deg [about holder x, y, z] (noise sd), dt mm:",
                  {n: (round(v['rot_deg'], 4), [round(x, 3) for x in v['rot_axes_deg']],
                       [round(x, 3) for x in v['std_rot_deg']], [round(x, 3) for x in v['t_mm']])
                   for n, v in s.items()})
    print(f"twin canvas supersampling of the captures: {results['twin_supersample']}")
    for ss, r in results["lens_map_holder"].items():
        noisy = [x["rot_deg"] for x in r["noisy"]]
        print(f"exact holder image through the lens map, canvas {ss}: noise-free {r['noise_free']['rot_deg']:.4f} deg "
              f"(about x, y, z {[round(x, 4) for x in r['noise_free']['rot_axes_deg']]}); sensor noise "
              f"({len(noisy)} draws): median {np.median(noisy):.4f}, max {max(noisy):.4f} deg; fit sd "
              f"{[round(x, 4) for x in r['noisy'][0]['std_rot_deg']]}")
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
