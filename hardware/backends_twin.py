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
from typing import Iterable

from glossrig.core.capture import TRUTH, atomic_write_json
from glossrig.core.errors import InputError

from .camera import ShotInfo, confirm_shot
from .errors import CameraError
from .plan import CapturePlan


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

    def configure(self, *, exposure_s: float, iso: int, aperture: float) -> None:
        self._settings = dict(exposure_s=float(exposure_s), iso=int(iso), aperture=float(aperture))

    def capture(self, path: Path) -> ShotInfo:
        if self._settings is None:
            raise CameraError("capture() before configure()", device="twin camera")
        path = Path(path)
        when = self.vr.now().isoformat(timespec="milliseconds")
        s = self._settings
        self.vr.shoot(path, s["exposure_s"], s["iso"], s["aperture"])
        info = confirm_shot(path, **s)
        truth = self.vr.truth()
        truth.update(self._truth_extra)
        atomic_write_json(path.parent / TRUTH, truth)
        return ShotInfo(exposure_s=info.exposure_s, iso=info.iso, aperture=info.aperture, camera=info.camera,
                        time=when)

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


def make_twin_backends(plan: CapturePlan) -> tuple[TwinLights, TwinCamera, TwinOperator]:
    """One :class:`VirtualRig` from the plan's rig and ``[twin]`` table, behind the three adapters."""
    from glossrig.core.materials import parse_material
    from glossrig.twin.effects import THESIS_FLUCTUATIONS, parse_effects
    from glossrig.twin.virtual_rig import VirtualRig

    if plan.checkerboard_views:
        raise InputError("the twin backends take no checkerboard views (use `glossrig simulate --target "
                         "checkerboard`); set [checkerboard] views = 0", path=plan.path)
    t = plan.twin
    try:
        material = parse_material(t.get("material", "lambert:0.8"))
        effects = {} if t.get("ideal", False) else dict(THESIS_FLUCTUATIONS)
        effects.update(parse_effects(t.get("effects")))
    except InputError as e:
        raise InputError(f"[twin]: {e}", path=plan.path) from None
    vr = VirtualRig(plan.rig, material, scale=float(t.get("scale", 0.25)), seed=int(t.get("seed", 0)),
                    effects=effects, spp=int(t.get("spp", 4)))
    extra = {"leds": list(plan.leds), "rotations": list(plan.rotations), "repeats": plan.repeats,
             "plan": plan.path}
    return TwinLights(vr), TwinCamera(vr, extra), TwinOperator(vr)
