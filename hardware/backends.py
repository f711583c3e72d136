"""Choosing the devices a capture runs on: ``--lights`` x ``--camera`` -> drivers + operator.

=================  =====================================================================
``--lights``        driver
=================  =====================================================================
``twin``            the virtual rig's LEDs (needs ``--camera twin``: one simulated rig)
``gpio``            :class:`~glossrig.hardware.lights.GpioRelayLights`, the thesis set-up
``serial-relay``    :class:`~glossrig.hardware.lights.NumatoRelayLights` on ``--relay-port``
``fake``            test-only: the GPIO driver on gpiozero's mock pins
=================  =====================================================================

=================  =====================================================================
``--camera``        driver
=================  =====================================================================
``twin``            the virtual rig's camera; the virtual rig also rotates the sample
``gphoto2``         :class:`~glossrig.hardware.camera.Gphoto2Camera` (python-gphoto2)
``fake``            test-only: the gphoto2 driver on :class:`~glossrig.hardware.fakes.FakeGphoto2`
=================  =====================================================================

With a real camera the operator rotates the sample when asked
(:class:`~glossrig.hardware.operator.ConsoleOperator`).
"""
from __future__ import annotations

from dataclasses import dataclass

from glossrig.core.errors import InputError

from .camera import Camera, Gphoto2Camera
from .errors import CaptureError
from .fakes import DeadRelayPin, FakeCameraBody, FakeGphoto2, env_spec, fake_lights_spec
from .lights import GpioRelayLights, Lights, NumatoRelayLights
from .operator import ConsoleOperator, Operator
from .plan import CapturePlan

LIGHTS = ("twin", "gpio", "serial-relay")
CAMERAS = ("twin", "gphoto2")
TEST_ONLY = ("fake",)


@dataclass
class Backends:
    lights: Lights
    camera: Camera
    operator: Operator
    names: dict

    def close(self) -> None:
        """Release both devices; the lights last (their close switches them off)."""
        try:
            self.camera.close()
        finally:
            self.lights.close()


def make_backends(plan: CapturePlan, lights: str, camera: str, *, relay_port: str | None = None,
                  relay_channels: int = 16, sample_ready: bool = False) -> Backends:
    if lights not in LIGHTS + TEST_ONLY:
        raise InputError(f"--lights must be one of {', '.join(LIGHTS)}, got {lights!r}")
    if camera not in CAMERAS + TEST_ONLY:
        raise InputError(f"--camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
    if (lights == "twin") != (camera == "twin"):
        raise InputError("the twin lights and the twin camera are one simulated rig: use --lights twin with "
                         "--camera twin")
    names = {"lights": lights, "camera": camera}
    if camera == "twin":
        try:
            from .backends_twin import make_twin_backends
        except ImportError as e:
            raise CaptureError(f"the twin backends are not available ({e})") from None
        tl, tc, op = make_twin_backends(plan)
        return Backends(tl, tc, op, names)

    if camera == "gphoto2":
        cam: Camera = Gphoto2Camera()
    else:
        cam = Gphoto2Camera(FakeGphoto2(FakeCameraBody.from_spec(env_spec("GLOSSRIG_FAKE_CAMERA"))),
                            extension=".dng", reconnect_wait_s=0.01)
    try:
        if lights == "gpio":
            li: Lights = GpioRelayLights(plan.rig)
        elif lights == "serial-relay":
            if not relay_port:
                raise InputError("--lights serial-relay needs --relay-port (e.g. /dev/ttyACM0)")
            li = NumatoRelayLights(plan.rig, relay_port, channels=relay_channels)
        else:
            from gpiozero.pins.mock import MockFactory
            factory = MockFactory()
            for led_id in fake_lights_spec(env_spec("GLOSSRIG_FAKE_LIGHTS")):
                factory.pin(plan.rig.led(led_id).gpio, pin_class=DeadRelayPin)
            li = GpioRelayLights(plan.rig, pin_factory=factory)
    except BaseException:
        cam.close()
        raise
    return Backends(li, cam, ConsoleOperator(sample_ready=sample_ready), names)
