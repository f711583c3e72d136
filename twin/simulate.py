"""``glossrig simulate``: synthesise a whole capture folder on the virtual rig.

For the sample target: per rotation, the calibration image (all LEDs on, ISO
3200, 30 s; thesis 4.2.1, the exact sum of single-LED renders), then per LED
and repeat the exposure sequence of Table 4.1 (ISO 320, f/11). For the
checkerboard target: views of the 9x6 board in varied poses for intrinsic
calibration. Files are written as they are made; the manifest is saved after
every file with ``complete: false`` and turned complete only at the end, so an
interrupted run never looks like a finished capture. ``truth.json`` holds what
was simulated; the pipeline never reads it.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from glossrig.core.capture import ImageEntry, Manifest, atomic_write_json, TRUTH
from glossrig.core.errors import InputError
from glossrig.core.materials import parse_material
from glossrig.core.rig import load_rig

from .effects import THESIS_FLUCTUATIONS, parse_effects


def prepare_out(out: Path) -> None:
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise InputError("output folder exists and is not empty; refusing to overwrite a capture", path=out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise InputError(f"output folder is not writable: {e.strerror}", path=out) from None


def rot_tag(rot: float) -> str:
    return f"r{rot:+04.0f}".replace("+", "p").replace("-", "m")


def simulate(rig_path, material_spec: str, leds_spec, rotations, repeats: int, scale: float, seed: int,
             effects_text: str | None, out, target: str = "sample", ideal: bool = False, spp: int = 4,
             keep_exr: bool = False, views: int = 12, progress: bool = True) -> Path:
    rig = load_rig(rig_path)
    material = parse_material(material_spec)
    if repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {repeats}")
    if not (0.01 <= scale <= 1.0):
        raise InputError(f"--scale must lie in [0.01, 1], got {scale}")
    effects = {} if ideal else dict(THESIS_FLUCTUATIONS)
    effects.update(parse_effects(effects_text))
    out = Path(out)
    if target == "checkerboard":
        prepare_out(out)
        return simulate_checkerboard(rig, out, scale=scale, seed=seed, views=views, spp=spp, progress=progress)
    if target != "sample":
        raise InputError(f"--target must be sample or checkerboard, got {target!r}")
    led_ids = rig.select_leds(leds_spec)
    prepare_out(out)

    from .virtual_rig import VirtualRig

    vr = VirtualRig(rig, material, scale=scale, seed=seed, effects=effects, spp=spp)
    man = Manifest(folder=out, rig=str(Path(rig.path).resolve()), material=material.label,
                   meta={"rig_name": rig.name, "source": "glossrig twin", "scale": scale})
    times = rig.exposure_times_s
    total = len(rotations) * (1 + len(led_ids) * repeats * len(times))
    bar = tqdm(total=total, desc="simulate", unit="img", disable=not progress)

    def record(file, role, leds, rot, rep, exposure, iso, aperture, digest, when, **extra):
        man.images.append(ImageEntry(file=file, role=role, leds=list(leds), rotation=rot, repeat=rep,
                                     exposure_s=exposure, iso=iso, aperture=aperture, time=when.isoformat(),
                                     sha256=digest, extra=extra))
        man.save()
        bar.update(1)

    for rot in rotations:
        vr.set_rotation(rot)
        tag = rot_tag(rot)
        vr.switch(rig.led_ids())
        when = vr.now()
        f = f"calibration_{tag}.dng"
        d = vr.shoot(out / f, rig.calibration_time_s, rig.calibration_iso, rig.calibration_aperture)
        record(f, "calibration", rig.led_ids(), rot, 0, rig.calibration_time_s, rig.calibration_iso,
               rig.calibration_aperture, d, when)
        for led in led_ids:
            vr.switch([led])
            if keep_exr:
                write_exr(out / "linear" / f"led{led:02d}_{tag}.exr", vr.led_radiance(led))
            for rep in range(repeats):
                for k, t in enumerate(times):
                    when = vr.now()
                    f = f"seq_{tag}_led{led:02d}_rep{rep}_e{k:02d}.dng"
                    d = vr.shoot(out / f, t, rig.sequence_iso, rig.sequence_aperture)
                    record(f, "sequence", [led], rot, rep, t, rig.sequence_iso, rig.sequence_aperture, d, when,
                           exposure_index=k)
    bar.close()
    truth = vr.truth()
    truth["leds"] = led_ids
    truth["rotations"] = list(rotations)
    truth["repeats"] = repeats
    atomic_write_json(out / TRUTH, truth)
    man.complete = True
    man.save()
    return out


def write_exr(path: Path, img: np.ndarray) -> None:
    import OpenEXR

    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(img, dtype=np.float32)}).write(str(path))


def checkerboard_poses(rig, lens, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses (board -> holder frame, mm) whose every inner corner is inside the
    image: distances 700-1100 mm from the camera, tilts up to 35 degrees, random roll."""
    import cv2

    rng = np.random.default_rng([seed, 5])
    nx, ny = rig.section("checkerboard")["inner_corners"]
    sq = float(rig.section("checkerboard")["square"])
    obj = np.array([[i * sq, j * sq, 0.0] for j in range(ny) for i in range(nx)])
    Rc, tc = rig.camera.pose()
    C = -Rc.T @ tc
    w, h = lens.size
    poses = []
    while len(poses) < n:
        dist = rng.uniform(700, 1100)
        tilt_x, tilt_y, roll = np.radians(rng.uniform(-35, 35)), np.radians(rng.uniform(-35, 35)), rng.uniform(0, 2 * np.pi)
        # board frame in camera coordinates: start facing the camera (board z = camera -z)
        Rb_cam = _rot_z(roll) @ _rot_x(tilt_x) @ _rot_y(tilt_y) @ np.diag([1.0, 1.0, 1.0])
        centre = np.array([(nx - 1) * sq / 2, (ny - 1) * sq / 2, 0.0])
        off = rng.uniform(-0.08, 0.08, 2) * dist
        t_cam = np.array([off[0], off[1], dist]) - Rb_cam @ centre
        img, _ = cv2.projectPoints(obj, cv2.Rodrigues(Rb_cam)[0], t_cam, lens.K, lens.dist)
        img = img.reshape(-1, 2)
        if (img.min(axis=0) > 20).all() and (img[:, 0].max() < w - 20) and (img[:, 1].max() < h - 20):
            # board normal must face the camera
            if (Rb_cam @ np.array([0, 0, 1.0]))[2] > 0.3:
                R_world = Rc.T @ Rb_cam
                t_world = Rc.T @ (t_cam - tc)
                poses.append((R_world, t_world))
    return poses


def _rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def simulate_checkerboard(rig, out: Path, scale: float, seed: int, views: int, spp: int, progress: bool) -> Path:
    from .dng import write_dng
    from .render import LensMap, render_array
    from .scene import SceneSpec, checkerboard_scene, new_workdir
    from .sensor import SensorModel
    from .virtual_rig import T0, SHOT_OVERHEAD_S
    from datetime import timedelta

    lens = LensMap.build(rig.camera, scale)
    sensor = SensorModel.from_rig(rig)
    R, t = rig.camera.pose()
    spec = SceneSpec(sample_radius=rig.cylinder_radius, camera_R=R, camera_t=t, canvas=lens.canvas,
                     focal=lens.focal, spp=lens.canvas_spp(max(spp, 8)))
    man = Manifest(folder=out, rig=str(Path(rig.path).resolve()), material="checkerboard",
                   meta={"rig_name": rig.name, "source": "glossrig twin", "scale": scale})
    poses = checkerboard_poses(rig, lens, views, seed)
    exposure, iso, aperture = 1 / 30, rig.sequence_iso, rig.sequence_aperture
    cam = rig.camera
    clock = 0.0
    with new_workdir() as wd:
        for k, (Rb, tb) in enumerate(tqdm(poses, desc="checkerboard", unit="view", disable=not progress)):
            scene = checkerboard_scene(rig, spec, Rb, tb, Path(wd))
            rad = lens.apply(render_array(scene, seed=seed * 100 + k))
            rng = np.random.default_rng([seed, 3, k])
            mosaic = sensor.expose(rad, exposure, iso, aperture, rng)
            when = T0 + timedelta(seconds=clock)
            f = f"checker_{k:02d}.dng"
            d = write_dng(out / f, mosaic, cfa=cam.cfa, black_level=cam.black_level, white_level=cam.white_level,
                          exposure_s=exposure, iso=iso, aperture=aperture, time=when)
            man.images.append(ImageEntry(file=f, role="checkerboard", leds=[], rotation=0.0, repeat=0,
                                         exposure_s=exposure, iso=iso, aperture=aperture, time=when.isoformat(),
                                         sha256=d, extra={"view": k}))
            man.save()
            clock += exposure + SHOT_OVERHEAD_S
    truth = {"target": "checkerboard", "scale": scale, "seed": seed, "image_size": list(lens.size),
             "camera_matrix": lens.K.tolist(), "distortion": list(cam.distortion),
             "board_poses_in_holder": [{"R": Rb.tolist(), "t_mm": tb.tolist()} for Rb, tb in poses],
             "camera_R_holder_to_camera": R.tolist(), "camera_t_mm": t.tolist(),
             "inner_corners": list(rig.section("checkerboard")["inner_corners"]),
             "square_mm": rig.section("checkerboard")["square"]}
    atomic_write_json(out / TRUTH, truth)
    man.complete = True
    man.save()
    return out
