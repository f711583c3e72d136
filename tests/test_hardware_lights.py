"""Lights drivers at the protocol boundary (thesis 4.1.1, fig. 4.4): the active-low GPIO
relay module on gpiozero's mock pins, and a Numato-protocol USB relay board simulated
on a pty pair (and on pyserial's loop://). Faults: a relay that does not switch, a
serial timeout."""
from __future__ import annotations

import pytest
import serial
from gpiozero.pins.mock import MockFactory, MockPin

from glossrig.core.errors import InputError
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.hardware.errors import LightsError
from glossrig.hardware.fakes import DeadRelayPin
from glossrig.hardware.lights import GpioRelayLights, Lights, NumatoRelayLights
from glossrig.hardware.serial_sims import NumatoRelaySim

RIG = load_rig(default_rig_path())


def pin_levels(factory, rig=RIG) -> dict[int, int]:
    return {led.id: int(factory.pin(led.gpio).state) for led in rig.leds}


def test_gpio_active_low_and_pin_map_of_the_rig():
    factory = MockFactory()
    lights = GpioRelayLights(RIG, pin_factory=factory)
    assert isinstance(lights, Lights)
    assert set(pin_levels(factory).values()) == {1}          # started with every relay off (pins high)
    lights.switch([7])
    levels = pin_levels(factory)
    assert levels[7] == 0 and sum(levels.values()) == 15      # LED 7 = GPIO17 pulled low, the rest high
    assert factory.pin(17).state == 0
    assert lights.state() == {7}
    lights.switch([5, 9])
    assert lights.state() == {5, 9} and factory.pin(24).state == 0 and factory.pin(13).state == 0
    lights.all_on()
    assert lights.state() == set(RIG.led_ids()) and set(pin_levels(factory).values()) == {0}
    lights.all_off()
    assert lights.state() == set() and set(pin_levels(factory).values()) == {1}


class RecordingPin(MockPin):
    """A mock pin that logs every level change, in order, across all pins."""

    log: list = []

    def _change_state(self, value):
        changed = super()._change_state(value)
        if changed:
            RecordingPin.log.append((self.info.name, bool(value)))
        return changed


def test_gpio_switching_never_lights_old_and_new_together():
    factory = MockFactory(pin_class=RecordingPin)
    lights = GpioRelayLights(RIG, pin_factory=factory)
    lights.switch([5])                      # LED 5 = GPIO24, LED 6 = GPIO4
    RecordingPin.log.clear()
    lights.switch([6])
    assert RecordingPin.log == [("GPIO24", True), ("GPIO4", False)]     # old one off (high) first, then on
    RecordingPin.log.clear()
    lights.close()                          # close switches off before releasing the pins
    assert RecordingPin.log[0] == ("GPIO4", True)


def test_gpio_relay_that_does_not_switch():
    factory = MockFactory()
    factory.pin(RIG.led(11).gpio, pin_class=DeadRelayPin)
    lights = GpioRelayLights(RIG, pin_factory=factory)
    lights.switch([10])
    with pytest.raises(LightsError, match=r"LED 11 \(35ii, relay channel 11, GPIO5\) did not switch on"):
        lights.switch([11, 12])
    lights.all_off()
    assert lights.state() == set()


def test_gpio_rejects_unknown_leds_and_bad_pin_maps(tmp_path):
    lights = GpioRelayLights(RIG, pin_factory=MockFactory())
    with pytest.raises(InputError, match=r"LED ids \[17\] are not in rig"):
        lights.switch([1, 17])
    text = default_rig_path().read_text().replace("gpio = 27 }", "gpio = 25 }")
    (tmp_path / "rig.toml").write_text(text)
    with pytest.raises(InputError, match=r"rig\.toml: LEDs 1 and 2 share GPIO pin 25"):
        GpioRelayLights(load_rig(tmp_path / "rig.toml"), pin_factory=MockFactory())


def test_numato_board_over_a_pty():
    with NumatoRelaySim(16) as sim:
        lights = NumatoRelayLights(RIG, sim.port, timeout_s=0.5)
        assert sim.commands[0] == "ver" and sim.on_relays() == set()
        lights.switch([1, 16])
        assert sim.on_relays() == {0, 15}                     # channel c -> board relay c - 1
        assert "relay writeall 8001" in sim.commands
        assert lights.state() == {1, 16}
        lights.all_on()
        assert sim.on_relays() == set(range(16))
        lights.close()
        assert sim.on_relays() == set()


def test_numato_relay_stuck_off():
    with NumatoRelaySim(16, stuck={3: False}) as sim:
        lights = NumatoRelayLights(RIG, sim.port, timeout_s=0.5)
        with pytest.raises(LightsError, match=r"LED 4 \(45i, relay channel 4\) did not switch on"):
            lights.switch([4, 5])
        lights.all_off()
        assert sim.on_relays() == set()


def test_numato_serial_timeout_is_retried_then_reported():
    # one lost reply: the command is sent again and the switch succeeds
    with NumatoRelaySim(16, mute_after=3, mute_count=1) as sim:
        lights = NumatoRelayLights(RIG, sim.port, timeout_s=0.15, retries=2)
        lights.switch([2])
        assert sim.on_relays() == {1}
        assert sim.commands.count("relay writeall 0002") == 2
    # a board that stays silent: a clear error naming the command and the wait
    with NumatoRelaySim(16, mute_after=3, mute_count=100) as sim:
        lights = NumatoRelayLights(RIG, sim.port, timeout_s=0.1, retries=1)
        with pytest.raises(LightsError, match=r"no reply to 'relay writeall 0002' within 0\.1 s after 2 attempts"):
            lights.switch([2])


def test_numato_on_pyserial_loop_url_is_not_mistaken_for_a_board():
    """loop:// echoes the command but never prompts: the driver must not take that as a reply."""
    with pytest.raises(LightsError, match=r"no reply to 'ver'"):
        NumatoRelayLights(RIG, "loop://", timeout_s=0.05, retries=0)


def test_numato_channel_count_must_fit_the_rig():
    with pytest.raises(InputError, match=r"relay channel 9, but the board has channels 1\.\.8"):
        NumatoRelayLights(RIG, serial.serial_for_url("loop://"), channels=8)
