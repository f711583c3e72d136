"""Engraver drivers at the protocol boundary (thesis 5.1.1): GRBL and a Roland RML-1
machine simulated on pty pairs, and the virtual engraver. Flow control keeps the
machines' buffers from overflowing; errors, alarms and a silent machine stop the
stream with a message naming the line; stop() acts at once; a toolpath outside the
bed or below the safe depth is refused before a single line is sent."""
from __future__ import annotations

import threading
import time

import pytest
import serial

from glossrig.hardware.engraver import EngraverStopped, GrblEngraver, RolandEngraver, SimulatedEngraver
from glossrig.hardware.errors import EngraverError
from glossrig.hardware.serial_sims import GrblSim, RolandSim
from glossrig.hardware.toolpath_check import MachineLimits, ToolpathError

LIM = MachineLimits(bed_mm=(100.0, 60.0), max_depth_mm=0.03, max_speed_mm_s=(100.0, 50.0, 100.0), source="test")


def eventually(cond, timeout=2.0):
    """The simulators run in their own thread: give them a moment to take the last bytes in."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def wait_until(cond, what: str, timeout=10.0, poll=0.001):
    """Poll ``cond`` every ``poll`` seconds until it holds; fail naming ``what`` after
    ``timeout`` seconds (a simulator or streaming thread that died must not hang the test)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(poll)


def gcode(n_cuts: int) -> str:
    head = ["G21 G90 G94", "M5", "G0 Z0.5"]
    body = []
    for i in range(n_cuts):
        x = 10 + 0.09 * i
        body += [f"G0 X{x:.2f} Y10.00", "G1 Z-0.020 F1200", f"G1 Y{40 + i % 7:.2f} F1200", "G0 Z0.500"]
    return "\n".join(head + body + ["G0 X0 Y0", "M2"])


def rml(n_cuts: int) -> str:
    cuts = "".join(f"PU{1000 + 9 * i},1000;PD{1000 + 9 * i},{4000 + 100 * (i % 7)};" for i in range(n_cuts))
    return "IN;!MC0;PA;VS20;!VZ20;!PZ-2,50;" + cuts + "PU0,0;!MC0;"


# ------------------------------------------------------------------ GRBL

def test_grbl_streams_everything_without_overflowing_its_rx_buffer():
    prog = gcode(50)
    with GrblSim(block_s=0.002) as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.05)
        seen = []
        rep = eng.stream(prog, progress=lambda done, total: seen.append((done, total)))
        sent = [ln.strip().upper() for ln in prog.splitlines()]
        assert sim.lines == sent                    # every line, in order, nothing lost
        assert not sim.overflow and sim.max_rx <= 128
        assert sim.max_rx > 64                      # and the buffer was really used (streaming, not ping-pong)
        assert rep.commands == len(sent) and seen[-1] == (len(sent), len(sent))
        assert eng.position() == (0.0, 0.0, 0.5) == rep.position
        assert eng.state() == "idle"
        assert sim.path[-1] == (0.0, 0.0, 0.5)
        eng.close()


def test_grbl_sim_detects_a_writer_without_flow_control():
    """The overflow check the previous test relies on does fire."""
    with GrblSim(block_s=0.01) as sim:
        port = serial.serial_for_url(sim.port, baudrate=115200, timeout=0.1)
        port.write(("\n".join(f"G1 X{i % 50} F600" for i in range(100)) + "\n").encode())
        port.flush()
        time.sleep(0.1)
        assert sim.overflow
        port.close()


def test_out_of_bed_or_too_deep_is_refused_before_any_line_is_sent():
    with GrblSim() as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.05)
        before = bytes(sim.received)
        with pytest.raises(ToolpathError, match=r"line 10: X=120\.000 mm is outside the bed"):
            eng.stream(gcode(1) + "\nG0 X120 Y5")
        with pytest.raises(ToolpathError, match=r"below the safe depth -0\.03 mm"):
            eng.stream(gcode(3).replace("G1 Z-0.020", "G1 Z-0.100"))
        time.sleep(0.05)
        assert sim.lines == [] and bytes(sim.received) == before     # not a byte after the handshake
        eng.close()


def test_grbl_error_stops_the_stream_and_names_the_line():
    prog = gcode(10)
    with GrblSim(error_at_line=5) as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.05)
        with pytest.raises(EngraverError) as ei:
            eng.stream(prog)
        msg = str(ei.value)
        assert "line 5 'G1 Z-0.020 F1200' rejected: error:33 (the motion command has an invalid target)" in msg
        assert eventually(lambda: sim.realtime[-2:] == [b"!", b"\x18"])     # feed hold, then soft reset
        assert eng.state() == "stopped"
        eng.close()


def test_grbl_serial_timeout_when_the_machine_goes_silent():
    with GrblSim(mute_after_lines=20, block_s=0.001) as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=0.5, poll_s=0.05)
        t0 = time.monotonic()
        with pytest.raises(EngraverError, match=r"no reply from GRBL for 0\.5 s .*serial timeout"):
            eng.stream(gcode(30))
        assert time.monotonic() - t0 < 3.0
        assert eventually(lambda: sim.realtime[-2:] == [b"!", b"\x18"])
        eng.close()


def test_grbl_in_alarm_refuses_to_stream():
    with GrblSim(alarm=True) as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.05)
        assert eng.state() == "alarm"
        with pytest.raises(EngraverError, match=r"ALARM state.*nothing was sent"):
            eng.stream(gcode(2))
        assert sim.lines == []
        eng.close()


def test_grbl_stop_acts_at_once_from_another_thread():
    with GrblSim(block_s=0.02) as sim:
        eng = GrblEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.02)
        errors = []

        def run():
            try:
                eng.stream(gcode(100))
            except EngraverError as e:
                errors.append(e)

        th = threading.Thread(target=run)
        th.start()
        wait_until(lambda: len(sim.path) >= 5, "GRBL to execute 5 moves")
        t0 = time.monotonic()
        eng.stop()
        th.join(timeout=5)
        assert not th.is_alive() and time.monotonic() - t0 < 1.0
        assert isinstance(errors[0], EngraverStopped)
        assert eventually(lambda: sim.state == "Alarm")
        executed = len(sim.path)
        time.sleep(0.1)
        assert len(sim.path) == executed < 100 * 4       # nothing moves after the reset
        assert sim.state == "Alarm"                      # GRBL wants re-homing after a reset in motion
        eng.close()


def test_grbl_that_never_answers_is_reported_at_connection():
    with RolandSim(mute=True) as sim:                    # something on the port that is not GRBL
        with pytest.raises(EngraverError, match="no GRBL start-up banner"):
            GrblEngraver(sim.port, LIM, startup_s=0.3, poll_s=0.05)


# ------------------------------------------------------------------ Roland

def test_roland_streams_with_buffer_flow_control():
    prog = rml(40)
    with RolandSim(capacity=160, command_s=0.0005) as sim:
        eng = RolandEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.005)
        rep = eng.stream(prog)
        sent = [c + ";" for c in prog.split(";") if c]
        assert sim.executed == sent and not sim.overflow
        assert "B" in sim.queries and rep.commands == len(sent)
        assert eng.position() == (0.0, 0.0, 0.5) and eng.state() == "idle"
        eng.close()


def test_roland_position_follows_what_the_machine_has_taken():
    with RolandSim(capacity=120, command_s=0.02) as sim:
        eng = RolandEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.01)
        th = threading.Thread(target=eng.stream, args=(rml(20),))
        th.start()
        wait_until(lambda: len(sim.executed) >= 12, "the Roland to execute 12 commands")
        pos = eng._pos
        th.join(timeout=10)
        # mid-stream the reported position is a point of the path, never ahead of the machine's buffer
        assert pos[0] is not None and 10.0 <= pos[0] <= 10.0 + 0.09 * 19 + 1e-9
        assert eng.position() == (0.0, 0.0, 0.5)
        eng.close()


def test_roland_refuses_a_cut_below_the_safe_depth_before_sending():
    with RolandSim() as sim:
        eng = RolandEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.01)
        with pytest.raises(ToolpathError, match=r"!PZ down height Z=-0\.050 mm is below the safe depth"):
            eng.stream(rml(3).replace("!PZ-2,50", "!PZ-5,50"))
        time.sleep(0.05)
        assert sim.buffer == b"" and sim.executed == [] and set(sim.queries) <= {"B"}
        eng.close()


def test_roland_serial_timeout():
    with RolandSim() as sim:
        eng = RolandEngraver(sim.port, LIM, timeout_s=0.3, poll_s=0.01)
        sim.mute = True
        with pytest.raises(EngraverError, match=r"no reply to ESC\.B within 0\.3 s \(serial timeout\)"):
            eng.stream(rml(5))
        assert sim.executed == []
        eng.close()


def test_roland_stop_discards_the_buffer():
    with RolandSim(capacity=400, command_s=0.01) as sim:
        eng = RolandEngraver(sim.port, LIM, timeout_s=2.0, poll_s=0.005)
        errors = []

        def run():
            try:
                eng.stream(rml(60))
            except EngraverError as e:
                errors.append(e)

        th = threading.Thread(target=run)
        th.start()
        wait_until(lambda: len(sim.executed) >= 5, "the Roland to execute 5 commands")
        eng.stop()
        th.join(timeout=5)
        assert isinstance(errors[0], EngraverStopped)
        assert eventually(lambda: sim.aborts == 1)
        n = len(sim.executed)
        time.sleep(0.1)
        assert len(sim.executed) <= n + 1 and sim.executed[-1] == "!MC0;"    # only the spindle-off ran after
        assert n < 2 * 60 + 8
        assert eng.state() == "stopped"
        eng.close()


# ------------------------------------------------------------------ virtual

def test_simulated_engraver_records_the_path_and_refuses_the_same_things():
    eng = SimulatedEngraver(LIM)
    rep = eng.stream(gcode(3))
    cuts = [m for m in eng.path if m.start[2] == -0.02 and m.end[2] == -0.02]
    assert [(m.start[:2], m.end[:2]) for m in cuts] == [((10.0, 10.0), (10.0, 40.0)), ((10.09, 10.0), (10.09, 41.0)),
                                                        ((10.18, 10.0), (10.18, 42.0))]
    assert rep.position == eng.position() == (0.0, 0.0, 0.5) and eng.state() == "idle"
    n = len(eng.received)
    with pytest.raises(ToolpathError):
        eng.stream(gcode(3) + "\nG1 Y70")
    assert len(eng.received) == n

    rml_eng = SimulatedEngraver(LIM, dialect="rml")
    rml_eng.stream(rml(2))
    assert [m.end for m in rml_eng.path if m.end[2] == -0.02][-1] == (10.09, 41.0, -0.02)


def test_simulated_engraver_stops_at_once():
    eng = SimulatedEngraver(LIM, time_scale=0.01)
    th = threading.Thread(target=lambda: pytest.raises(EngraverStopped, eng.stream, gcode(100)))
    th.start()
    wait_until(lambda: len(eng.path) >= 3, "the simulated engraver to make 3 moves")
    eng.stop()
    th.join(timeout=5)
    n = len(eng.path)
    assert eng.state() == "stopped" and n < 100 * 4
    time.sleep(0.05)
    assert len(eng.path) == n
