"""The twin as capture backends: lights, camera and "operator" sharing one virtual rig.

:class:`glossrig.twin.virtual_rig.VirtualRig` renders the rig of the plan's rig file
with the plan's ``[twin]`` material, scale, seed and effects; these thin adapters give
it the device protocols of :mod:`glossrig.hardware.lights`, :mod:`.camera` and
:mod:`.operator`, so the capture orchestrator runs the twin exactly as it runs the
real rig (design.md: one plan, virtual or real devices). The camera's shots are
confirmed from the DNG's own metadata like a real camera's, carry the virtual rig's
simulated capture clock (thesis 4.2.3 time line) as their manifest time, and each
shot refreshes ``truth.json`` next to the raw files - what was simulated, which the
pipeline never reads.
"""
from __future__ import annotations

from pathlib import Path
from collections.abc import Iterable

from glossrig.core.atomic import atomic_write_json
from glossrig.core.capture import TRUTH, read_truth
from glossrig.core.errors import InputError

from .camera import ShotInfo, confirm_shot
from .errors import CameraError
from .plan import CapturePlan


_CLAMPED = "negative_radiance_pixels_clamped"


class TwinLights:
    """The virtual rig's LEDs (any subset on at once, like the relay board)."""

    def __init__(self, vr):
        self.vr = vr
        self._ids = frozenset(vr.rig.led_ids())

    def switch(self, led_ids: Iterable[int]) -> None:
        ids = sorted({int(i) for i in led_ids})
        unknown = [i for i in ids if i not in self._ids]
        if unknown:
            raise InputError(f"LED ids {unknown} are not in rig {self.vr.rig.name!r}", path=self.vr.rig.path)
        self.vr.switch(ids)

    def all_on(self) -> None:
        self.switch(self._ids)

    def all_off(self) -> None:
        self.switch(())

    def state(self) -> frozenset[int]:
        return frozenset(self.vr.on)

    def close(self) -> None:
        self.all_off()


class TwinCamera:
    """The virtual rig's camera: writes DNGs (``twin.dng``) at the configured settings."""

    extension = ".dng"

    def __init__(self, vr, truth_extra: dict | None = None):
        self.vr = vr
        self._settings: dict | None = None
        self._truth_extra = dict(truth_extra or {})
        self._next: tuple[dict, float] | None = None
        self._carried: dict | None = None

    def configure(self, *, exposure_s: float, iso: int, aperture: float) -> None:
        self._settings = dict(exposure_s=float(exposure_s), iso=int(iso), aperture=float(aperture))

    def provenance(self) -> dict:
        """What makes this camera's images besides the plan: Mitsuba's variant and version, Dr.Jit's
        version and the sensor model's path. Recorded in the manifest (``camera_provenance``): the
        same seed makes the same bytes only with the same renderer and sensor path - the CPU and GPU
        variants' renders differ in the last bits, and the NumPy reference sensor's sequential
        Poisson stream turns that into other noise (validation/twin/variants.md)."""
        from importlib.metadata import PackageNotFoundError, version

        from glossrig.twin import sensor_drjit
        from glossrig.twin.mitsuba_env import mitsuba

        def ver(name: str) -> str | None:
            try:
                return version(name)
            except PackageNotFoundError:
                return None

        return {"mitsuba_variant": mitsuba().variant(), "mitsuba": ver("mitsuba"), "drjit": ver("drjit"),
                "sensor_model": "drjit-llvm" if sensor_drjit.available() else "numpy-reference"}

    def next_shot(self, shot, at_s: float) -> None:
        """The orchestrator names the planned shot the next :meth:`capture` takes and its
        time on the plan's schedule: the image then gets its own random stream and time
        (:meth:`glossrig.twin.virtual_rig.VirtualRig.shoot`), so a resumed capture is
        byte-identical to an uninterrupted one."""
        image = dict(role=shot.role, rotation=float(shot.rotation), leds=tuple(shot.leds), repeat=int(shot.repeat),
                     exposure_index=int(shot.exposure_index), view=shot.view)
        self._next = (image, float(at_s))

    def capture(self, path: Path) -> ShotInfo:
        if self._settings is None:
            raise CameraError("capture() before configure()", device="twin camera")
        path = Path(path)
        s = self._settings
        image, at_s = self._next if self._next is not None else (None, None)
        self._next = None
        if at_s is not None:
            self.vr.clock_s = at_s
        when = self.vr.now().isoformat(timespec="milliseconds")
        self.vr.shoot(path, s["exposure_s"], s["iso"], s["aperture"], image=image, at_s=at_s)
        info = confirm_shot(path, **s)
        self._write_truth(path.parent)
        return ShotInfo(exposure_s=info.exposure_s, iso=info.iso, aperture=info.aperture, camera=info.camera,
                        time=when)

    def _write_truth(self, folder: Path) -> None:
        """Refresh ``truth.json``. The negative-radiance counts of renders an interrupted
        earlier run made (and this one need not repeat) are carried over, so the truth of a
        resumed capture equals that of an uninterrupted one."""
        if self._carried is None:
            self._carried = {}
            try:
                old = read_truth(folder / TRUTH)
                if isinstance(old.get(_CLAMPED), dict):
                    self._carried = dict(old[_CLAMPED])
            except InputError:
                pass
        truth = self.vr.truth()
        truth.update(self._truth_extra)
        truth[_CLAMPED] = dict(sorted({**self._carried, **truth.get(_CLAMPED, {})}.items()))
        atomic_write_json(folder / TRUTH, truth)

    def close(self) -> None:
        pass


class TwinOperator:
    """Rotating the sample is setting the virtual rig's rotation."""

    def __init__(self, vr):
        self.vr = vr

    def rotate_to(self, rotation_deg: float) -> None:
        self.vr.set_rotation(rotation_deg)

    def place_checkerboard(self, view: int, views: int) -> None:
        raise CameraError("the twin's checkerboard views are made by `glossrig simulate --target checkerboard`",
                          device="twin")


def _same_material(a, b) -> bool:
    return (a.kind, a.ward, a.albedo, a.path) == (b.kind, b.ward, b.albedo, b.path)


def _check_sample_label(plan: CapturePlan, material) -> None:
    """The plan's ``sample`` becomes the manifest's material label. Where that label names a
    material (a spec or a scenes/materials name) it must be the one the twin renders: a
    capture labelled sample_2_6 that holds a lambert:0.8 render is silently wrong data.
    Free-text labels ("white paper, batch 3") cannot be compared and are left alone."""
    from glossrig.core.models.materials import parse_material

    try:
        named = parse_material(plan.sample)
    except InputError:
        return
    if not _same_material(named, material):
        raise InputError(f"the plan's sample {plan.sample!r} (the manifest's material label) is not the material "
                         f"the twin would render, [twin] material = {plan.twin['material']!r}; make them agree",
                         path=plan.path)


def make_twin_backends(plan: CapturePlan) -> tuple[TwinLights, TwinCamera, TwinOperator]:
    """One :class:`VirtualRig` from the plan's rig and ``[twin]`` table, behind the three adapters."""
    from glossrig.core.models.materials import parse_material
    from glossrig.twin.effects import parse_effects, rig_fluctuations
    from glossrig.twin.virtual_rig import VirtualRig

    if plan.checkerboard_views:
        raise InputError("the twin backends take no checkerboard views (use `glossrig simulate --target "
                         "checkerboard`); set [checkerboard] views = 0", path=plan.path)
    t = plan.twin
    if "material" not in t:
        # no default: a twin that silently renders some other material than the plan's
        # sample writes a capture whose manifest lies about what it holds
        raise InputError("the twin backends need the material to render: the plan has no [twin] key 'material' "
                         "(ward:..., lambert:ALBEDO, measured:PATH, mitsuba:FILE.xml or a scenes/materials name; glossrig design "
                         "exposures writes it)", path=plan.path)
    try:
        material = parse_material(str(t["material"]))
        effects = {} if t.get("ideal", False) else rig_fluctuations(plan.rig)
        effects.update(parse_effects(t.get("effects")))
    except InputError as e:
        raise InputError(f"[twin]: {e}", path=plan.path) from None
    _check_sample_label(plan, material)
    vr = VirtualRig(plan.rig, material, scale=float(t.get("scale", 0.25)), seed=int(t.get("seed", 0)),
                    effects=effects, spp=int(t.get("spp", 4)))
    extra = {"leds": list(plan.leds), "rotations": list(plan.rotations), "repeats": plan.repeats,
             "plan": plan.path}
    return TwinLights(vr), TwinCamera(vr, extra), TwinOperator(vr)
