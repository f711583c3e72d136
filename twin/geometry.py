"""Meshes of the rig's non-primitive parts, built with trimesh (issue 2).

Holder box, the holder marker's red frame and white patch, the three curved
cylinder markers and the LED housings. Everything in millimetres in the
holder frame; :mod:`glossrig.twin.scene` converts to metres for Mitsuba.
"""
from __future__ import annotations

import numpy as np
import trimesh

from glossrig.core.calibration.markers import cylinder_marker_angles, cylinder_marker_radius, holder_marker_corners


def holder_box(rig, recess: float = 0.04) -> trimesh.Trimesh:
    """The holder; its front face ``recess`` mm behind the marker plane z = depth / 2."""
    h = rig.holder
    box = trimesh.creation.box(extents=(h.width, h.height, h.depth - recess))
    box.apply_translation((0.0, h.top - h.height / 2, -recess / 2))
    return box


def _quad(corners: np.ndarray) -> trimesh.Trimesh:
    """A quad from corners ordered UL, UR, LL, LR, facing +z."""
    faces = np.array([[0, 2, 3], [0, 3, 1]])
    return trimesh.Trimesh(vertices=corners, faces=faces, process=False)


def holder_marker_meshes(rig, lift: float = 0.02) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """Red square (outer, ``lift`` mm behind the marker plane) and white patch (inner, on
    the marker plane of :func:`holder_marker_corners`, which the pipeline assumes); the
    holder's front face is recessed by ``2 * lift`` (:func:`holder_box`)."""
    outer = holder_marker_corners(rig).copy()
    inner = holder_marker_corners(rig, inner=True).copy()
    outer[:, 2] -= lift
    return _quad(outer), _quad(inner)


def curved_patch(radius: float, a0: float, a1: float, y0: float, y1: float, segments: int = 48) -> trimesh.Trimesh:
    """A patch of the cylinder x^2 + z^2 = radius^2 between angles a0..a1 (about +y from
    +z to +x) and heights y0..y1, normals outwards. Chord sag with 48 segments over
    18 degrees is below 0.001 mm."""
    a = np.linspace(a0, a1, segments + 1)
    top = np.stack([radius * np.sin(a), np.full_like(a, y1), radius * np.cos(a)], axis=-1)
    bot = np.stack([radius * np.sin(a), np.full_like(a, y0), radius * np.cos(a)], axis=-1)
    v = np.concatenate([top, bot])
    n = len(a)
    f = []
    for i in range(segments):
        # counter-clockwise seen from outside (outward normal)
        f.append([i, n + i, n + i + 1])
        f.append([i, n + i + 1, i + 1])
    return trimesh.Trimesh(vertices=v, faces=np.array(f), process=False)


def cylinder_marker_meshes(rig) -> list[trimesh.Trimesh]:
    cm = rig.cylinder_markers
    a = cylinder_marker_angles(rig)
    y0 = cm.centre_height - cm.side / 2
    y1 = cm.centre_height + cm.side / 2
    # The red squares lie exactly on the marker radius the pipeline assumes; the white
    # band is drawn just below it (twin.scene).
    r = cylinder_marker_radius(rig)
    return [curved_patch(r, a[2 * k], a[2 * k + 1], y0, y1) for k in range(cm.count)]


def led_housing(position, radius: float = 4.0, length: float = 10.0, gap: float = 0.5) -> trimesh.Trimesh:
    """A black cylinder behind the LED, its front face ``gap`` mm behind the emitter,
    its axis pointing at the cylinder axis."""
    p = np.asarray(position, float)
    d = -np.array([p[0], 0.0, p[2]])
    d /= np.linalg.norm(d)
    m = trimesh.creation.cylinder(radius=radius, height=length, sections=24)
    # trimesh's cylinder is centred on the origin along +z: turn +z onto d.
    m.apply_transform(trimesh.geometry.align_vectors([0, 0, 1.0], d))
    m.apply_translation(p - d * (gap + length / 2))
    return m
