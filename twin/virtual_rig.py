"""The virtual rig: the twin as a device (lights + camera sharing one simulated rig).

Renders once per (LED, sample rotation) to linear radiance and derives every
exposure and repeat in the sensor model (issue 2: never re-render per
exposure). The hardware layer's twin backends and ``glossrig simulate`` both
drive this class; the geometry it renders with (LED positions after
``led_position_error``, sample radius, rotation offset) is what truth.json
records.

A simulated capture clock advances by each shot's exposure plus the rig's
per-shot overhead (thesis 4.2.3: ~4 min per 18-exposure sequence whose
exposures sum to 61.0 s, i.e. ~9.9 s per shot), so the LED drift and the
manifest's timestamps follow the real capture's time line. The clock starts at
:data:`T0` so captures are reproducible. A capture driven by a plan (the
orchestrator's twin backends, which ``glossrig simulate`` uses too) gives each
shot its place in the plan - its time on the plan's schedule and its identity
for its own random stream - so a resumed capture is byte-identical to an
uninterrupted one.
"""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.models.materials import Material
from glossrig.core.rig import Rig

from .effects import EffectState
from .render import DEFAULT_SPP, LensMap, render_array
from .sensor import frame_rng
from .scene import LED_RGB, MM, ROTATING_KINDS, SceneSpec, new_workdir, sample_scene

T0 = datetime(2026, 1, 1, 9, 0, 0, tzinfo=timezone.utc)
SHOT_OVERHEAD_S = (240.0 - 61.00725) / 18.0   # Table 4.1's exposures sum to 61.00725 s


class VirtualRig:
    def __init__(self, rig: Rig, material: Material, *, scale: float = 0.25, seed: int = 0,
                 effects: dict[str, float] | None = None, spp: int = DEFAULT_SPP):
        from .sensor import SensorModel


        if not (0.01 <= scale <= 1.0):
            raise InputError(f"scale must lie in [0.01, 1], got {scale}")
        if (effects or {}).get("sample_rotation_offset") and material.kind not in ROTATING_KINDS:
            # an isotropic BRDF is unchanged by a turn about the normal, f(R wi, R wo) = f(wi, wo): a
            # lambert or RGL `measured` sample (the RGL data here are isotropic) is not turned by the
            # twin at all, so the effect would be recorded in the truth but absent from every image
            raise InputError(f"--effects sample_rotation_offset: the twin does not turn a {material.kind!r} "
                             f"sample (it turns {' and '.join(ROTATING_KINDS)} materials); an isotropic "
                             "sample turned about its normal gives the same images, so the effect would "
                             "not be in the capture")
        self.rig, self.material, self.scale, self.seed, self.spp = rig, material, scale, seed, spp
        self.effects = EffectState(dict(effects or {}), seed, rig.led_ids(),
                                   drift_period_s=rig.lighting.drift_period_s)
        self.sensor = SensorModel.from_rig(rig)
        self.lens = LensMap.build(rig.camera, scale)
        self.camera_R, self.camera_t = rig.camera.pose()
        self.sample_radius = rig.cylinder_radius + self.effects.get("sample_radius_error")
        self.led_positions = {led.id: self.effects.led_position(led) for led in rig.leds}
        self.intensity = rig.lighting.radiant_intensity_W_sr
        self._workdir = new_workdir()
        spec = SceneSpec(sample_radius=self.sample_radius, camera_R=self.camera_R, camera_t=self.camera_t,
                         canvas=self.lens.canvas, focal=self.lens.focal, spp=self.lens.canvas_spp(spp), led_positions=self.led_positions)
        self._spec = spec
        self.scene, self.params = sample_scene(rig, material, spec, Path(self._workdir.name))
        self._points = None
        self._vignette = self.effects.vignetting_factor(self.lens.size, self.lens.K)
        self._hot = self.effects.hot_pixel_mask(self.lens.size, seed)
        self._cache: dict[tuple, np.ndarray] = {}
        self._hooks: _DnHooks | None = None
        self._prepared = None       # the sensor input of the last single-LED render shot (SensorModel.prepare)
        self.clamped_pixels: dict[tuple, int] = {}
        self.rotation = 0.0
        self.on: list[int] = []
        self.clock_s = 0.0
        self.frame = 0

    # --- device-like interface ---------------------------------------------
    def set_rotation(self, deg: float) -> None:
        self.rotation = float(deg)
        if self.material.kind in ROTATING_KINDS:
            self._cache.clear()     # renders depend on the rotation

    def switch(self, led_ids) -> None:
        ids = [int(i) for i in led_ids]
        for i in ids:
            self.rig.led(i)
        self.on = ids

    def now(self) -> datetime:
        return T0 + timedelta(seconds=self.clock_s)

    def shoot(self, path, exposure_s: float, iso: int, aperture: float, overwrite: bool = False, *,
              image: dict | None = None, at_s: float | None = None) -> str:
        """Expose the current light state and write a DNG; returns its sha256.

        ``image``: what the image is in its plan (``role``, ``rotation``, ``leds``,
        ``repeat``, ``exposure_index``, ``view``; :func:`glossrig.twin.sensor.image_rng`);
        its noise and LED jitter then come from that image's own random stream. ``at_s``:
        its time on the plan's schedule (seconds from :data:`T0`), which sets the LED drift
        and the DNG's timestamp. With both, an image is the same bytes whatever was shot
        before it in this process (resume). Without them (ad-hoc use) the stream is the
        process's frame counter and the time its running clock."""
        from .dng import write_dng
        from .sensor import image_rng

        if at_s is not None:
            self.clock_s = float(at_s)
        rng = image_rng(self.seed, **image) if image is not None else frame_rng(self.seed, self.frame)
        radiance, gain = self._shot_radiance(self.on, rng)
        cam = self.rig.camera
        if self._hooks is None:
            self._hooks = _DnHooks(self.effects, self._hot, cam)
        hooks = self._hooks if self._hooks.active else None
        mosaic = self.sensor.expose(radiance, exposure_s, iso, aperture, rng, gain=gain, effects=hooks,
                                    frame_index=self.frame)
        when = self.now()
        digest = write_dng(path, mosaic, cfa=cam.cfa, black_level=cam.black_level, white_level=cam.white_level,
                           exposure_s=exposure_s, iso=iso, aperture=aperture, time=when, overwrite=overwrite)
        self.clock_s += exposure_s + SHOT_OVERHEAD_S
        self.frame += 1
        return digest

    # --- radiometry -----------------------------------------------------------
    def points_mm(self) -> np.ndarray:
        """Holder-frame position (mm) of the surface each output pixel sees (0 where none)."""
        if self._points is None:

            scene, _ = sample_scene(self.rig, self.material, self._spec, Path(self._workdir.name), aov=True)
            aov = render_array(scene, spp=1)
            # the aov integrator writes only its AOVs: channels 0-2 "pos", 3-5 "nn"
            self._points = self.lens.apply(aov[..., 0:3], nearest=True) / MM
            del scene
        return self._points

    def led_radiance(self, led_id: int) -> np.ndarray:
        """Linear radiance (h, w, 3) W m^-2 sr^-1 with only ``led_id`` on at its nominal
        output (emission pattern and vignetting included; gain and stray light not)."""
        key = (led_id, self.rotation if self.material.kind in ROTATING_KINDS else 0.0)
        if key not in self._cache:
            from .mitsuba_env import mitsuba

            mi = mitsuba()
            pos = self.led_positions[led_id]
            self.params["led.position"] = mi.Point3f(*[p * MM for p in pos])
            self.params["led.intensity.value"] = mi.Color3f(*[self.intensity * c for c in LED_RGB])
            if self.material.kind in ROTATING_KINDS:
                rot = math.radians(self.rotation + self.effects.get("sample_rotation_offset"))
                self.params["sample.bsdf.tangent_rotation"] = rot
            self.params.update()
            img = self.lens.apply(render_array(self.scene, seed=self.seed * 1000 + led_id))
            neg = img < 0
            if neg.any():
                # Mitsuba's `measured` plugin (RGL RGB data, Dupuy & Jakob 2018) can return
                # negative values where its RGB interpolation overshoots near grazing angles;
                # radiance cannot be negative, so these are clamped and counted in the truth.
                # keyed like the cache: a rotation-independent render is recorded at rotation 0,
                # whichever rotation this process happened to render it at (resume-stable truth)
                self.clamped_pixels[key] = int(neg.any(axis=-1).sum())
                np.maximum(img, 0.0, out=img)
            if self.effects.get("led_emission") > 0:      # the surface points only where they are used
                f = self.effects.emission_factor(led_id, pos, self.points_mm())
                if f is not None:
                    img *= f[..., None]
            if self._vignette is not None:
                img *= self._vignette[..., None]
            self._cache[key] = img
        return self._cache[key]

    def image_radiance(self, led_ids, rng: np.random.Generator) -> np.ndarray:
        """Radiance (h, w, 3) of the image with ``led_ids`` on: each LED's render times its
        gain (jitter and drift, drawn from ``rng``) plus its stray light."""
        w, h = self.lens.size
        out = np.zeros((h, w, 3), np.float32)
        for i in led_ids:
            g = self.effects.led_gain(i, self.clock_s, rng)
            out += g * self.led_radiance(i)
            s = self._stray(i)
            if s is not None:
                out += g * s
        return out

    def _stray(self, led_id: int):
        """LED ``led_id``'s stray-light radiance (broadcastable to (h, w, 3)), or None."""
        s = self.effects.stray_radiance(self.intensity, float(np.linalg.norm(self.led_positions[led_id])))
        if not s:
            return None
        return s * np.asarray(LED_RGB, np.float32) * (self._vignette[..., None] if self._vignette is not None else 1.0)

    def _shot_radiance(self, led_ids, rng: np.random.Generator):
        """(radiance, gain) whose product is :meth:`image_radiance` (the same draws from
        ``rng``): a single LED without stray light is its cached render, prepared for the
        sensor once for all the exposures of its sequence, and its gain, which the sensor
        model applies in its own pass (no (h, w, 3) copy per exposure, issue 19)."""
        ids = list(led_ids)
        if len(ids) == 1 and self._stray(ids[0]) is None:
            rad = self.led_radiance(ids[0])
            if self._prepared is None or self._prepared.radiance is not rad:
                self._prepared = None                    # one at a time: a sequence is one LED's
                self._prepared = self.sensor.prepare(rad)
            return self._prepared, self.effects.led_gain(ids[0], self.clock_s, rng)
        return self.image_radiance(ids, rng), 1.0

    # --- truth ------------------------------------------------------------------
    def truth(self) -> dict:
        cam = self.rig.camera
        material = self.material.to_json()
        if self.material.kind == "mitsuba":
            material["evaluate"] = ("glossrig.twin.mitsuba_material.MitsubaBRDF.from_json(truth['material'])"
                                    ".table(samples, rotation_offset_deg=truth['sample_rotation_offset_deg'])")
        return {
            "material": material,
            "rig": {"path": self.rig.path, "name": self.rig.name},
            "scale": self.scale, "seed": self.seed, "spp": self.spp, "supersample": self.lens.supersample,
            "image_size": list(self.lens.size),
            "camera_matrix": self.lens.K.tolist(), "distortion": list(cam.distortion),
            "camera_R_holder_to_camera": self.camera_R.tolist(), "camera_t_mm": self.camera_t.tolist(),
            "cylinder_R_in_holder": np.eye(3).tolist(), "cylinder_t_mm": [0.0, 0.0, 0.0],
            "sample_radius_mm": self.sample_radius, "sample_height_mm": self.rig.sample_height,
            "led_positions_mm": {str(k): list(v) for k, v in self.led_positions.items()},
            "led_radiant_intensity_W_sr": self.intensity, "led_rgb": list(LED_RGB),
            "sample_rotation_offset_deg": self.effects.get("sample_rotation_offset"),
            "effects": self.effects.to_json(),
            "shot_overhead_s": SHOT_OVERHEAD_S, "clock_start": T0.isoformat(),
            "negative_radiance_pixels_clamped": {f"led{k[0]}_rot{k[1]:g}": v
                                                 for k, v in sorted(self.clamped_pixels.items())},
        }


class _DnHooks:
    """Adapter giving the sensor model (``post_dn`` stage) the effects that act on
    the raw signal: nonlinearity, black-level offset, hot pixels. ``active``: whether
    any of them is on (without, the sensor model is given no hooks and rounds in its
    fast kernel)."""

    def __init__(self, effects: EffectState, hot, camera):
        self.effects, self.hot, self.camera = effects, hot, camera
        self.active = hot is not None or effects.get("sensor_nonlinearity") > 0 \
            or effects.get("black_level_offset") != 0
        self._black: np.ndarray | None = None

    def post_dn(self, dn, ctx):
        h, w = dn.shape
        if self._black is None or self._black.shape != dn.shape:
            self._black = np.tile(ctx.sensor.black_2x2().astype(np.float32), (h // 2, w // 2))
        return self.effects.apply_dn(dn, self._black, self.camera.white_level, ctx.exposure_s,
                                     ctx.sensor.conversion_gain(ctx.iso), self.hot).astype(np.float32, copy=False)
