"""Marker geometry of the rig (thesis 4.1.4, eq. 4.18 and 4.22-4.24).

Shared by the twin (which builds them) and the pipeline (which finds them):
* the holder marker - a white patch framed by a red square on the holder's
  front face, in the holder frame;
* three red squares on a white paper band around the top of the cylinder, in
  the cylinder frame, side ``w`` with gaps of ``w`` (eq. 4.22-4.23).

Departure from eq. 4.22-4.23: the thesis puts corner i at arc length ``i * w``
(i = 1..6) from the cylinder's angle 0; here the band is centred on angle 0
(the camera direction in the nominal rig), corner i at ``(i - 3.5) * w / r``.
Both are the same pattern; centring only fixes where angle 0 is.
"""
from __future__ import annotations

import numpy as np


def holder_marker_corners(rig, inner: bool = False) -> np.ndarray:
    """Outer (or inner, white-patch) corners of the holder marker, ``(4, 3)`` mm in
    the holder frame, ordered upper-left, upper-right, lower-left, lower-right as
    seen from the camera with the cylinder axis up (thesis eq. 4.18: P1..P4)."""
    m = rig.holder.marker
    w, hh = m.outer_width, m.outer_height
    if inner:
        w, hh = w - 2 * m.frame, hh - 2 * m.frame
    z = rig.holder.depth / 2
    yc = m.centre_y
    return np.array([[-w / 2, yc + hh / 2, z], [w / 2, yc + hh / 2, z],
                     [-w / 2, yc - hh / 2, z], [w / 2, yc - hh / 2, z]], dtype=np.float64)


def cylinder_marker_radius(rig) -> float:
    """Radius of the printed marker surface: the sample-wrapped cylinder plus the marker
    paper (thesis 4.3.2: r^c includes the paper's thickness)."""
    return rig.cylinder.radius_with_sample + rig.cylinder_markers.paper_thickness


def cylinder_marker_angles(rig) -> np.ndarray:
    """Angles (rad, about +y from +z towards +x) of the 2*count vertical marker edges."""
    cm = rig.cylinder_markers
    r = cylinder_marker_radius(rig)
    n = 2 * cm.count
    return (np.arange(1, n + 1) - (n + 1) / 2) * cm.side / r


def cylinder_marker_corners(rig) -> np.ndarray:
    """The 4*count marker corners ``(12, 3)`` in the cylinder frame (eq. 4.22-4.24):
    first the upper row (y = h_u), then the lower row (y = h_l), each ordered by
    angle. Grouped per marker: corners [2k, 2k+1] of each row bound marker k."""
    cm = rig.cylinder_markers
    r = cylinder_marker_radius(rig)
    a = cylinder_marker_angles(rig)
    hu = cm.centre_height + cm.side / 2
    hl = cm.centre_height - cm.side / 2
    upper = np.stack([r * np.sin(a), np.full_like(a, hu), r * np.cos(a)], axis=-1)
    lower = np.stack([r * np.sin(a), np.full_like(a, hl), r * np.cos(a)], axis=-1)
    return np.concatenate([upper, lower])
