"""The pre-send toolpath check (thesis 5.1): bed, safe depth, axis speeds, and what it
refuses because it cannot check it. Also: the fabrication code's own G-code and RML-1
pass it for the thesis machine and fail it for a smaller bed."""
from __future__ import annotations

import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.rig import REPO_ROOT
from glossrig.hardware.toolpath_check import (MachineLimits, ToolpathError, check_toolpath, load_machine_limits,
                                              parse_gcode, parse_rml, read_toolpath)

LIM = MachineLimits(bed_mm=(100.0, 50.0), max_depth_mm=0.03, max_height_mm=20.0,
                    max_speed_mm_s=(100.0, 50.0, 100.0), source="test limits")


def refused(text: str, dialect="gcode", match=None):
    tp = read_toolpath(text, dialect=dialect, source="t.path")
    with pytest.raises(ToolpathError, match=match) as ei:
        check_toolpath(tp, LIM)
    assert str(ei.value).startswith("t.path: toolpath refused before sending anything")
    return str(ei.value)


def accepted(text: str, dialect="gcode"):
    tp = read_toolpath(text, dialect=dialect, source="t.path")
    check_toolpath(tp, LIM)
    return tp


GOOD = """G21 G90 G94 G17
M5 ; scalpel
F1200
G0 Z0.5
G0 X10 Y10
G1 Z-0.02 F600
G1 Y40 F1200 (cut along y)
G0 Z0.5
G0 X0 Y0
M2
"""


def test_a_scratch_program_inside_the_bed_passes():
    tp = accepted(GOOD)
    assert [m.end for m in tp.moves][-1] == (0.0, 0.0, 0.5)
    assert tp.commands[1] == (2, "M5")            # comments stripped from what is sent
    assert tp.position_after(len(tp.commands) - 1) == (0.0, 0.0, 0.5)


@pytest.mark.parametrize("bad, what", [
    ("G0 X100.5 Y10", r"X=100\.500 mm is outside the bed \(0\.\.100 mm\)"),
    ("G0 X10 Y-0.2", r"Y=-0\.200 mm is outside the bed"),
    ("G1 Z-0.04 F60", r"line 4: move to Z=-0\.040 mm is below the safe depth -0\.03 mm"),
    ("G0 Z25", r"above the machine's 20 mm"),
])
def test_outside_the_bed_or_too_deep(bad, what):
    refused(f"G21 G90\nG0 Z0.5\nG0 X1 Y1\n{bad}\n", match=what)


def test_inches_are_converted():
    refused("G20 G90\nG0 X4 Y1\n", match=r"X=101\.600 mm")      # 4 in = 101.6 mm
    accepted("G20 G90\nG0 X3.9 Y1\n")


def test_relative_moves_are_followed_and_unknown_starts_refused():
    refused("G90 G0 X90 Y10\nG91\nG0 X5\nG0 X6\n", match=r"line 4: X=101\.000")
    refused("G91\nG0 X5\n", match="relative move of X from an unknown position")


def test_an_arc_bulging_out_of_the_bed_is_refused_though_its_ends_are_inside():
    # half circle from (10, 45) to (30, 45) around (20, 45), clockwise: over the top, up to y = 55 > 50
    refused("G90 G0 X10 Y45 Z0.5\nG2 X30 Y45 I10 J0 F600\n", match=r"line 2: Y=55\.000 mm is outside the bed")
    accepted("G90 G0 X10 Y45 Z0.5\nG3 X30 Y45 I10 J0 F600\n")     # counter-clockwise: under, down to y = 35
    refused("G90 G0 X10 Y25 Z0.5\nG3 X10 Y25 I0 J15 F600\n", match=r"Y=55\.000")    # full circle
    refused("G90 G0 X10 Y10 Z0.5\nG2 X20 Y10 I3 J0 F600\n", match="not on the arc's circle")


@pytest.mark.parametrize("line, what", [
    ("G92 X0 Y0", "shifts the coordinate system"),
    ("G28", "stored machine position"),
    ("G53 G0 X0", "machine coordinates"),
    ("G55", "another work coordinate system"),
    ("G2 X10 Y10 R5 F100", "R-format arcs"),
    ("G1 X5 Y5 #7", "cannot parse"),
    ("G1 X5 Y5 Q7 F100", "word Q is not understood"),
    ("G1 X5 Y5", "before any feed rate"),
])
def test_what_cannot_be_checked_is_refused(line, what):
    refused(f"G21 G90\nG0 X1 Y1 Z1\n{line}\n", match=what)


def test_axis_speed_limits_of_thesis_5_1_1():
    refused("G90 G0 X0 Y0 Z0.5\nG1 Y10 F3600\n", match=r"moves Y at 60\.0 mm/s, above the machine's 50 mm/s")
    accepted("G90 G0 X0 Y0 Z0.5\nG1 X10 F3600\n")       # 60 mm/s is fine along x


RML_GOOD = "IN;!MC0;PA;VS20;!VZ20;!PZ-2,50;PU1000,1000;PD1000,4000;PU2000,1000;PD2000,4000;PU0,0;!MC0;"


def test_rml_units_and_pen_heights():
    tp = accepted(RML_GOOD, "rml")
    cut = [m for m in tp.moves if m.end[2] == -0.02 and m.start[2] == -0.02]
    assert [(m.start[:2], m.end[:2]) for m in cut] == [((10.0, 10.0), (10.0, 40.0)), ((20.0, 10.0), (20.0, 40.0))]
    assert tp.position_after(len(tp.commands) - 1) == (0.0, 0.0, 0.5)


def test_rml_refusals():
    refused(RML_GOOD.replace("!PZ-2,50", "!PZ-5,50"), "rml", match=r"!PZ down height Z=-0\.050 mm is below")
    refused(RML_GOOD.replace("PD2000,4000", "PD2000,5200"), "rml", match=r"Y=52\.000 mm is outside the bed")
    refused("IN;PA;Z1000,1000,-400;", "rml", match=r"move to Z=-4\.000 mm is below the safe depth")
    refused("IN;PR;PU100,100;", "rml", match="relative move from an unknown position")
    refused("IN;XX12;", "rml", match="unknown RML-1 instruction")
    refused("IN;!ZZ5;", "rml", match="not known to the pre-send check")
    refused(RML_GOOD.replace("VS20", "VS80"), "rml", match=r"moves Y at 80\.0 mm/s")


def test_rml_one_instruction_per_line_reports_line_numbers():
    text = "IN;\nPA;\n!PZ-2,50;\nPU1000,1000;\nPD1000,9000;\n"
    msg = refused(text, "rml")
    assert "line 5: Y=90.000 mm" in msg


def test_limits_from_the_machine_description():
    lim = load_machine_limits()
    assert lim.bed_mm == (305.0, 230.0) and lim.max_depth_mm == 0.03
    assert lim.max_speed_mm_s == (100.0, 50.0, 100.0) and lim.rml_units_per_mm == 100
    with pytest.raises(InputError, match="machine description not found"):
        load_machine_limits("/nonexistent/machine.toml")


def test_bad_machine_description_names_the_file(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text((REPO_ROOT / "scenes" / "engraver_roland.toml").read_text().replace("bed_mm = [305.0, 230.0]",
                                                                                   "bed_mm = [305.0]"))
    with pytest.raises(InputError, match=r"m\.toml: \[machine\] bed_mm must be \[x, y\]"):
        load_machine_limits(p)


def test_toolpath_files(tmp_path):
    (tmp_path / "a.nc").write_text(GOOD)
    assert read_toolpath(tmp_path / "a.nc").dialect == "gcode"
    (tmp_path / "a.rml").write_text(RML_GOOD)
    assert read_toolpath(tmp_path / "a.rml").dialect == "rml"
    with pytest.raises(InputError, match="toolpath file not found"):
        read_toolpath(tmp_path / "missing.nc")
    (tmp_path / "a.txt").write_text(GOOD)
    with pytest.raises(InputError, match="G-code or RML-1"):
        read_toolpath(tmp_path / "a.txt")


def test_the_fabrication_codes_output_passes_and_fails_where_it_should():
    from glossrig.core.fabrication.gcode import write_gcode
    from glossrig.core.fabrication.machine import load_machine
    from glossrig.core.fabrication.rml import write_rml
    from glossrig.core.fabrication.toolpath import Toolpath

    machine = load_machine()
    path = Toolpath(x=np.array([5.0, 5.09, 5.18]), y_start=np.array([5.0, 5.0, 5.0]),
                    y_end=np.array([60.0, 60.0, 60.0]), home=(0.0, 0.0), cut_z=-machine.cut_depth_mm,
                    safe_z=machine.safe_height_mm)
    lim = load_machine_limits()
    g = parse_gcode(write_gcode(path, machine).splitlines(), "fab.nc")
    r = parse_rml(write_rml(path, machine), "fab.rml", units_per_mm=lim.rml_units_per_mm)
    for tp in (g, r):
        check_toolpath(tp, lim)
        cuts = [m for m in tp.moves if m.start[2] is not None and m.start[2] < 0 and m.end[2] < 0]
        assert len(cuts) == 3 and all(abs(m.end[1] - 60.0) < 1e-9 for m in cuts)
        small = MachineLimits(bed_mm=(50.0, 50.0), max_depth_mm=lim.max_depth_mm, source="small bed")
        with pytest.raises(ToolpathError, match=r"Y=60\.000 mm is outside the bed"):
            check_toolpath(tp, small)
