"""``glossrig simulate``: synthesise a whole capture folder on the virtual rig.

For the sample target: per rotation, the calibration image (all LEDs on, ISO
3200, 30 s; thesis 4.2.1, the exact sum of single-LED renders), then per LED
and repeat the exposure sequence of Table 4.1 (ISO 320, f/11). For the
checkerboard target: views of the 9x6 board in varied poses for intrinsic
calibration. Files are written as they are made; the manifest is saved after
every file with ``complete: false`` and turned complete only at the end, so an
interrupted run never looks like a finished capture. ``truth.json`` holds what
was simulated; the pipeline never reads it.

The sample capture runs as a capture plan through the hardware layer's
orchestrator on the twin backends, exactly as ``glossrig capture --lights twin
--camera twin`` does: the same file names (:func:`glossrig.core.capture.image_stem`),
the same folder (capture.json, raw files, rig.toml, truth.json) and the same
resume. Every image draws its noise and LED fluctuations from its own random
stream, keyed by what it is in the plan (:func:`glossrig.twin.sensor.image_rng`),
and takes its time (LED drift, timestamps) from its place on the plan's
schedule, so ``resume=True`` completes an interrupted capture byte-identical to
an uninterrupted one. The options that determine the images are recorded in the
manifest (``simulate``) and a resume with other options is refused.
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from glossrig.core.atomic import atomic_write_json
from glossrig.core.capture import (RIG_COPY, TRUTH, ImageEntry, Manifest, check_rig_copy, check_rotation_tags,
                                   image_stem, load_manifest, rotation_tag, sha256_file)
from glossrig.core.errors import InputError
from glossrig.core.models.materials import material_sha256, parse_material
from glossrig.core.progress import progress_enabled
from glossrig.core.rig import load_rig

from .effects import parse_effects, rig_fluctuations
from .render import DEFAULT_SPP


def prepare_out(out: Path, resume: bool = False) -> None:
    """The capture folder may be written: missing or empty (or, with ``resume``, holding
    the interrupted capture to complete), and writable."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", path=out)
    if not resume and out.exists() and any(out.iterdir()):
        raise InputError("output folder exists and is not empty; refusing to overwrite a capture", path=out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise InputError(f"output folder is not writable: {e.strerror}", path=out) from None


def parse_twin_material(spec: str):
    """:func:`glossrig.core.models.materials.parse_material`, and a Mitsuba BSDF description
    loaded once, so a bad file fails before anything is written."""
    material = parse_material(spec)
    if material.kind == "mitsuba":
        from .mitsuba_material import load_bsdf

        load_bsdf(material)
    return material


#: The manifest key under which ``simulate`` records the options that determine its images.
OPTIONS_KEY = "simulate"


def plan_sha256(options: dict) -> str:
    """The sha256 of a simulated capture's plan (the manifest's ``plan.sha256``): the plan's
    text is the sorted JSON of the options that determine the images (``OPTIONS_KEY``), the
    material as :func:`capture_identity` names it."""
    return hashlib.sha256(json.dumps(capture_identity(options), sort_keys=True).encode()).hexdigest()


def capture_identity(options: dict) -> dict:
    """What a capture's options say about its images: the options, but a material read from a
    file whose sha256 is recorded (``material_sha256``) is named by the kind of its spec
    (``measured``, ``mitsuba``, or the packaged name) and that sha256 alone - the file's path
    says where the file was, not what it was, so the same material reached from another
    checkout or folder is the same capture. Options without the sha256 (inline ``ward:`` and
    ``lambert:`` specs, or the record of a capture made before it was recorded) are
    themselves."""
    if options.get("material_sha256") is None:
        return dict(options)
    spec = str(options.get("material", ""))
    return {**options, "material": spec.split(":", 1)[0] if spec.startswith(("measured:", "mitsuba:")) else spec}


def twin_effects(rig, effects_text: str | None, ideal: bool = False) -> dict:
    """The non-idealities a capture of ``rig`` is simulated with: the rig's own LED fluctuations
    (unless ``ideal``; :func:`.effects.rig_fluctuations`) updated by ``--effects`` (``name=value,...``)."""
    effects = {} if ideal else rig_fluctuations(rig)
    effects.update(parse_effects(effects_text))
    return effects


def sample_options(rig, material_spec: str, leds_spec, rotations, repeats: int, scale: float, seed: int,
                   effects: dict, spp: int) -> dict:
    """The options that determine a sample capture's images, as its manifest records them
    (``OPTIONS_KEY``): a resume, or an extension by LEDs, must give the same."""
    led_ids = rig.select_leds(leds_spec)
    rotations = [float(r) for r in rotations]
    if len(set(rotations)) != len(rotations):
        raise InputError(f"--rotations lists an angle twice: {rotations}")
    check_rotation_tags(rotations)
    return {"target": "sample", "rig_name": rig.name, "material": material_spec,
            "material_sha256": material_sha256(material_spec), "leds": list(led_ids),
            "rotations": rotations, "repeats": int(repeats), "scale": float(scale), "seed": int(seed),
            "effects": dict(sorted(effects.items())), "spp": int(spp)}


def checkerboard_options(rig, scale: float, seed: int, views: int, spp: int) -> dict:
    """The options that determine a checkerboard capture's views, as its manifest records them."""
    return {"target": "checkerboard", "rig_name": rig.name, "scale": float(scale), "seed": int(seed),
            "views": int(views), "spp": int(spp)}


def differing_options(recorded: dict, options: dict) -> list[str]:
    """The keys in which a capture's recorded simulate options (``OPTIONS_KEY``) and a
    command's differ, sorted; a key one of them lacks differs (``material_sha256`` is missing
    from the record of a capture made before glossrig recorded it). Where both record the
    material's sha256 the material is compared by :func:`capture_identity` (its content, not
    its path); otherwise by its spec's text."""
    if recorded.get("material_sha256") is not None and options.get("material_sha256") is not None:
        recorded, options = capture_identity(recorded), capture_identity(options)
    return [k for k in sorted(set(recorded) | set(options)) if recorded.get(k) != options.get(k)]


def describe_differences(recorded: dict, options: dict, keys: list[str], recorded_as: str = "capture",
                         given_as: str = "now") -> str:
    """``key: capture X, now Y; ...`` for the keys of :func:`differing_options`; a key the
    record lacks is said to be unrecorded (a capture of an earlier glossrig)."""
    return "; ".join(f"{k}: {recorded_as} {recorded[k]!r}, {given_as} {options.get(k)!r}" if k in recorded else
                     f"{k}: not recorded by the glossrig that made the capture, {given_as} {options.get(k)!r}"
                     for k in keys)


def _check_resume(out: Path, options: dict) -> bool:
    """With ``--resume``: whether there is a capture to continue in ``out`` (False: start
    afresh in an empty or missing folder). Refuses a folder that holds no capture, a
    capture not made by ``glossrig simulate``, or one made with other options - the
    resumed images would not belong to the same capture."""
    from glossrig.core.capture import MANIFEST

    man = out / MANIFEST
    if not man.is_file():
        if out.is_dir() and any(out.iterdir()):
            raise InputError("--resume: the folder holds no capture manifest (capture.json); nothing to resume "
                             "(nothing was changed)", path=out)
        return False
    try:
        old = load_manifest(out).meta.get(OPTIONS_KEY)
    except InputError as e:
        raise InputError(f"--resume: the manifest cannot be read ({e})", path=man) from None
    if not isinstance(old, dict):
        raise InputError("--resume: this capture was not made by glossrig simulate (its manifest records no "
                         "simulate options); nothing was changed", path=man)
    diff = differing_options(old, options)
    if diff:
        what = describe_differences(old, options, diff)
        raise InputError(f"--resume: the capture was made with other options ({what}); rerun with the original "
                         "options or choose another --out (nothing was changed)", path=man)
    return True


def simulate(rig_path, material_spec: str, leds_spec, rotations, repeats: int, scale: float, seed: int,
             effects_text: str | None, out, target: str = "sample", ideal: bool = False, spp: int = DEFAULT_SPP,
             keep_exr: bool = False, views: int = 12, progress: bool = True, resume: bool = False) -> Path:
    """Synthesise a capture folder (module docstring); ``resume`` completes an interrupted one.

    The sample capture is a capture plan (thesis 4.2.3) run by the hardware layer's
    orchestrator on the twin backends - the very code ``glossrig capture --lights twin
    --camera twin`` runs - so both write the same folder: ``capture.json``, the raw files
    under the names of :func:`glossrig.core.capture.image_stem`, ``rig.toml`` (the rig
    the capture was made with) and ``truth.json``. Every image has its own random stream
    and its time on the plan's schedule, so a resumed capture is byte-identical to an
    uninterrupted one; resume checks every recorded file against its sha256 and retakes
    what is missing or damaged."""
    rig = load_rig(rig_path)
    material = parse_twin_material(material_spec)
    if repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {repeats}")
    if not (0.01 <= scale <= 1.0):
        raise InputError(f"--scale must lie in [0.01, 1], got {scale}")
    if int(seed) < 0:
        raise InputError(f"--seed must be >= 0, got {seed}")
    effects = twin_effects(rig, effects_text, ideal)
    out = Path(out)
    if target == "checkerboard":
        if views < 1:
            raise InputError(f"--views must be >= 1, got {views}")
        options = checkerboard_options(rig, scale, seed, views, spp)
        resuming = _check_resume(out, options) if resume else False
        prepare_out(out, resume=resume)
        return simulate_checkerboard(rig, out, scale=scale, seed=seed, views=views, spp=spp, progress=progress,
                                     options=options, resume=resuming)
    if target != "sample":
        raise InputError(f"--target must be sample or checkerboard, got {target!r}")
    options = sample_options(rig, material_spec, leds_spec, rotations, repeats, scale, seed, effects, spp)
    led_ids, rotations = options["leds"], options["rotations"]
    resuming = _check_resume(out, options) if resume else False
    prepare_out(out, resume=resume)

    from glossrig.hardware.backends_twin import TwinCamera, TwinLights, TwinOperator
    from glossrig.hardware.orchestrator import run_capture
    from glossrig.hardware.plan import CapturePlan

    from .virtual_rig import SHOT_OVERHEAD_S, VirtualRig

    cal = (rig.calibration_time_s, rig.calibration_iso, rig.calibration_aperture)
    plan = CapturePlan(
        path="glossrig simulate", text_sha256=plan_sha256(options), rig=rig,
        rig_path=Path(rig.path).resolve(), sample=material.label, rotations=tuple(rotations), leds=tuple(led_ids),
        repeats=int(repeats), exposures_s=tuple(rig.exposure_times_s), iso=rig.sequence_iso,
        aperture=rig.sequence_aperture, calibration=True, calibration_exposure_s=cal[0], calibration_iso=cal[1],
        calibration_aperture=cal[2], checkerboard_views=0, checkerboard_leds=(), checkerboard_exposure_s=cal[0],
        checkerboard_iso=cal[1], checkerboard_aperture=cal[2], overhead_s_per_shot=SHOT_OVERHEAD_S, settle_s=0.0,
        twin={"material": material_spec, "scale": float(scale), "seed": int(seed), "spp": int(spp),
              "effects": ",".join(f"{k}={v!r}" for k, v in sorted(effects.items())), "ideal": not effects})
    vr = VirtualRig(rig, material, scale=scale, seed=seed, effects=effects, spp=spp)
    camera = TwinCamera(vr, {"leds": list(led_ids), "rotations": list(rotations), "repeats": int(repeats)})
    meta = {"source": "glossrig twin", "scale": scale, OPTIONS_KEY: options}
    run_capture(plan, out, lights=TwinLights(vr), camera=camera, operator=TwinOperator(vr),
                backends={"lights": "twin", "camera": "twin"}, resume=resuming,
                show_progress=progress_enabled(progress), meta=meta)
    if keep_exr:
        for rot in rotations:
            vr.set_rotation(rot)
            for led in led_ids:
                f = out / "linear" / f"led{led:02d}_rot{rotation_tag(rot)}.exr"
                if not f.exists():
                    write_exr(f, vr.led_radiance(led))
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
    nx, ny = rig.checkerboard.inner_corners
    sq = rig.checkerboard.square
    obj = np.array([[i * sq, j * sq, 0.0] for j in range(ny) for i in range(nx)])
    Rc, tc = rig.camera.pose()
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


def simulate_checkerboard(rig, out: Path, scale: float, seed: int, views: int, spp: int, progress: bool,
                          options: dict | None = None, resume: bool = False) -> Path:
    """Checkerboard views for intrinsic calibration. Each view's render seed, noise stream
    and time depend only on its number, so ``resume`` (keep the recorded views whose
    files match their sha256, re-make the rest) ends byte-identical to one run."""
    from .dng import write_dng
    from .render import LensMap, render_array
    from .scene import SceneSpec, checkerboard_scene, new_workdir
    from .sensor import SensorModel
    from .virtual_rig import T0, SHOT_OVERHEAD_S
    from datetime import timedelta
    from glossrig.core.atomic import atomic_write_bytes

    lens = LensMap.build(rig.camera, scale)
    sensor = SensorModel.from_rig(rig)
    R, t = rig.camera.pose()
    spec = SceneSpec(sample_radius=rig.cylinder_radius, camera_R=R, camera_t=t, canvas=lens.canvas,
                     focal=lens.focal, spp=lens.canvas_spp(max(spp, 8)))
    rig_bytes = Path(rig.path).read_bytes()
    done: dict[int, ImageEntry] = {}
    if resume:
        man = load_manifest(out)
        check_rig_copy(out, rig_bytes, where=out, then="refusing to mix rigs in one capture (--resume)")
        for im in man.images:
            f = out / im.file
            if im.role == "checkerboard" and f.is_file() and sha256_file(f) == im.sha256:
                done.setdefault(int(im.extra.get("view", -1)), im)
        man.complete = False
    else:
        man = Manifest(folder=out, rig=RIG_COPY, material="checkerboard",
                       meta={"rig_name": rig.name, "rig_source": str(Path(rig.path).resolve()),
                             "source": "glossrig twin", "scale": scale, OPTIONS_KEY: dict(options or {})})
    atomic_write_bytes(out / RIG_COPY, rig_bytes)
    poses = checkerboard_poses(rig, lens, views, seed)
    exposure, iso, aperture = 1 / 30, rig.sequence_iso, rig.sequence_aperture
    cam = rig.camera
    man.images = [done[k] for k in sorted(done) if 0 <= k < views]
    man.save()
    with new_workdir() as wd:
        for k, (Rb, tb) in enumerate(tqdm(poses, desc="checkerboard", unit="view", disable=not progress_enabled(progress))):
            if k in done:
                continue
            f = image_stem("checkerboard", view=k) + ".dng"
            for stale in (out / f, *out.glob(f".{f}.*.part")):    # unrecorded or half-written: re-made
                stale.unlink(missing_ok=True)
            scene = checkerboard_scene(rig, spec, Rb, tb, Path(wd))
            rad = lens.apply(render_array(scene, seed=seed * 100 + k))
            rng = np.random.default_rng([seed, 3, k])
            mosaic = sensor.expose(rad, exposure, iso, aperture, rng)
            when = T0 + timedelta(seconds=k * (exposure + SHOT_OVERHEAD_S))
            d = write_dng(out / f, mosaic, cfa=cam.cfa, black_level=cam.black_level, white_level=cam.white_level,
                          exposure_s=exposure, iso=iso, aperture=aperture, time=when)
            man.images.append(ImageEntry(file=f, role="checkerboard", leds=[], rotation=0.0, repeat=0,
                                         exposure_s=exposure, iso=iso, aperture=aperture, time=when.isoformat(),
                                         sha256=d, extra={"view": k}))
            man.images.sort(key=lambda im: int(im.extra.get("view", 0)))
            man.save()
    truth = {"target": "checkerboard", "scale": scale, "seed": seed, "image_size": list(lens.size),
             "camera_matrix": lens.K.tolist(), "distortion": list(cam.distortion),
             "board_poses_in_holder": [{"R": Rb.tolist(), "t_mm": tb.tolist()} for Rb, tb in poses],
             "camera_R_holder_to_camera": R.tolist(), "camera_t_mm": t.tolist(),
             "inner_corners": list(rig.checkerboard.inner_corners),
             "square_mm": rig.checkerboard.square}
    atomic_write_json(out / TRUTH, truth)
    man.complete = True
    man.save()
    return out
