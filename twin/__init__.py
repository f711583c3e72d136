"""glossrig.twin: the virtual rig.

A Mitsuba 3 scene of the cylinder, markers, 16 LEDs and camera; a sensor model;
named non-ideal effects; a writer of captures in the same format the real
camera produces (DNG + capture.json), plus a separate truth.json.
"""
