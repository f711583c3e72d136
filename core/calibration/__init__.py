"""glossrig.core.calibration: Geometric calibration (thesis 4.3.1-4.3.2, 4.3.4): raw reading and linearisation, demosaicing, intrinsics, markers, holder and cylinder poses, lamp positions."""
