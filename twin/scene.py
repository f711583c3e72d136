"""The Mitsuba 3 scene of the rig (issue 2): cylinder with the sample, black paper,
marker band, holder with its marker, LED housings, one movable point LED, camera.

Scene units are metres (so a point light's intensity in W/sr gives radiance in
W m^-2 sr^-1); the rig file is in millimetres. Only one point light is in the
scene: it is moved to each LED in turn through ``mi.traverse`` (Mitsuba notes:
the direct integrator samples one light per sample, so an all-LEDs image is the
exact sum of single-LED renders instead).
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from glossrig.core.calibration.markers import cylinder_marker_radius
from glossrig.core.models.materials import Material

from . import geometry
from .mitsuba_env import mitsuba

MM = 1e-3
# Linear-sRGB colour of a 10000 K LED behind an opal diffuser (thesis 4.1.3),
# normalised to G = 1: a cool white. Approximate (blackbody chromaticity).
LED_RGB = (0.80, 1.0, 1.18)
PAPER_WHITE = 0.8
MARKER_RED = (0.55, 0.04, 0.04)
BLACK_PAPER = 0.03
BLACK_PLASTIC = 0.04


def _ply(mesh, folder: Path, name: str) -> str:
    m = mesh.copy()
    m.apply_scale(MM)
    path = folder / f"{name}.ply"
    m.export(path)
    return str(path)


def _diffuse(value) -> dict:
    if isinstance(value, (int, float)):
        value = (value, value, value)
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(value)}}


#: material kinds whose BSDF turns with the sample (``sample.bsdf.tangent_rotation``)
ROTATING_KINDS = ("ward", "mitsuba")


def material_bsdf(material: Material, tangent_rotation_rad: float = 0.0) -> dict:
    """Mitsuba BSDF dict of a sample material (grey Ward parameters apply to R, G, B,
    a coloured one's per channel; a stock Mitsuba BSDF inside ``glossrig_rotated``).
    ``tangent_rotation_rad``: the sample rotation, for the materials that turn with it
    (:data:`ROTATING_KINDS`)."""
    if material.kind == "ward":
        w = material.ward
        rgb = material.rgb or {"rho_d": [w.rho_d] * 3, "rho_s": [w.rho_s] * 3}
        return {"type": "glossrig_ward", "rho_d": list(rgb["rho_d"]), "rho_s": list(rgb["rho_s"]),
                "alpha_x": w.alpha_x, "alpha_y": w.alpha_y, "lobe_rotation": w.lobe_rotation,
                "tangent_rotation": tangent_rotation_rad}
    if material.kind == "lambert":
        return _diffuse(material.albedo)
    if material.kind == "measured":
        return {"type": "measured", "filename": material.path}
    if material.kind == "mitsuba":
        from .mitsuba_material import rotated_dict

        return rotated_dict(material, tangent_rotation_rad)
    raise ValueError(material.kind)


def _axis_to_world(radius: float, y0: float, y1: float):
    """Mitsuba cylinder (local z in [0,1], radius 1) -> world: local x -> +z
    (angle 0 = camera side), local y -> +x, local z -> +y."""
    mi = mitsuba()
    m = np.array([[0, radius, 0, 0], [0, 0, y1 - y0, y0], [radius, 0, 0, 0], [0, 0, 0, 1.0]])
    m[:3, :] *= MM
    return mi.ScalarTransform4f(m)


@dataclass
class SceneSpec:
    """What the scene is built from; the truth of the geometry actually rendered."""

    sample_radius: float                      # mm (nominal + sample_radius_error)
    camera_R: np.ndarray                      # holder -> camera (OpenCV)
    camera_t: np.ndarray                      # mm
    canvas: tuple[int, int]                   # pinhole render size (w, h)
    focal: float                              # pinhole focal length, px
    spp: int = 4
    led_positions: dict = field(default_factory=dict)   # id -> (x, y, z) mm


def _camera_dict(spec: SceneSpec) -> dict:
    mi = mitsuba()
    R, t = spec.camera_R, spec.camera_t
    C = -R.T @ t
    forward = R.T @ np.array([0, 0, 1.0])
    down = R.T @ np.array([0, 1.0, 0])
    w, h = spec.canvas
    fov = math.degrees(2 * math.atan(w / 2 / spec.focal))
    return {
        "type": "perspective", "fov": fov, "fov_axis": "x",
        "near_clip": 0.01, "far_clip": 10.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=(C * MM).tolist(), target=((C + forward * 100) * MM).tolist(),
                                                 up=(-down).tolist()),
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent", "sample_count": spec.spp},
    }


def sample_scene(rig, material: Material, spec: SceneSpec, workdir: Path, aov: bool = False):
    """Load the rig scene with ``material`` on the sample. Returns ``(scene, params)``;
    ``params['led.position']`` / ``params['led.intensity.value']`` move and scale the LED,
    ``params['sample.bsdf.tangent_rotation']`` turns a Ward or Mitsuba sample (:data:`ROTATING_KINDS`)."""
    mi = mitsuba()
    cyl = rig.cylinder
    cm = rig.cylinder_markers
    hs = rig.sample_height / 2
    r = spec.sample_radius
    red, white = geometry.holder_marker_meshes(rig)
    d = {
        "type": "scene",
        "integrator": ({"type": "aov", "aovs": "pos:position,nn:sh_normal"} if aov else {"type": "direct"}),
        "camera": _camera_dict(spec),
        "sample": {"type": "cylinder", "to_world": _axis_to_world(r, -hs, hs), "bsdf": material_bsdf(material)},
        "paper_low": {"type": "cylinder", "to_world": _axis_to_world(r, cyl.bottom, -hs), "bsdf": _diffuse(BLACK_PAPER)},
        "paper_mid": {"type": "cylinder", "to_world": _axis_to_world(r, hs, cm.band_bottom), "bsdf": _diffuse(BLACK_PAPER)},
        "band": {"type": "cylinder", "to_world": _axis_to_world(cylinder_marker_radius(rig) - 0.02, cm.band_bottom, cm.band_top),
                 "bsdf": _diffuse(PAPER_WHITE)},
        "paper_top": {"type": "cylinder", "to_world": _axis_to_world(r, cm.band_top, cyl.top), "bsdf": _diffuse(BLACK_PAPER)},
        "holder": {"type": "ply", "filename": _ply(geometry.holder_box(rig), workdir, "holder"), "bsdf": _diffuse(BLACK_PLASTIC)},
        "holder_red": {"type": "ply", "filename": _ply(red, workdir, "holder_red"), "bsdf": _diffuse(MARKER_RED)},
        "holder_white": {"type": "ply", "filename": _ply(white, workdir, "holder_white"), "bsdf": _diffuse(PAPER_WHITE)},
        "led": {"type": "point", "position": [0.0, 0.0, 0.3], "intensity": {"type": "rgb", "value": list(LED_RGB)}},
    }
    for k, m in enumerate(geometry.cylinder_marker_meshes(rig)):
        d[f"marker{k}"] = {"type": "ply", "filename": _ply(m, workdir, f"marker{k}"), "bsdf": _diffuse(MARKER_RED)}
    housing_r = rig.lighting.housing_radius
    for led_id, pos in spec.led_positions.items():
        d[f"housing{led_id}"] = {"type": "ply", "filename": _ply(geometry.led_housing(pos, housing_r), workdir, f"housing{led_id}"),
                                 "bsdf": _diffuse(BLACK_PLASTIC)}
    scene = mi.load_dict(d)
    return scene, mi.traverse(scene)


def checkerboard_scene(rig, spec: SceneSpec, board_R: np.ndarray, board_t: np.ndarray, workdir: Path,
                       radiance: float = 4.0):
    """A 9x6-inner-corner checkerboard (25 mm squares) lit by a uniform environment.

    ``board_R, board_t`` map board coordinates (mm; origin at the first inner corner,
    x along the 9 corners, y along the 6, z out of the board's back) into the holder
    frame. The texture is a tiny bitmap sampled with nearest filtering, so the
    square edges are exact."""
    mi = mitsuba()
    nx, ny = rig.checkerboard.inner_corners
    sq = rig.checkerboard.square
    border = 1  # one white square around the pattern
    cols, rows = nx + 1 + 2 * border, ny + 1 + 2 * border
    tex = np.ones((rows, cols, 3), np.float32) * 0.85
    for i in range(nx + 1):
        for j in range(ny + 1):
            if (i + j) % 2 == 0:
                tex[j + border, i + border] = 0.03
    # board-frame corners of the whole card
    x0, y0 = -(1 + border) * sq, -(1 + border) * sq
    x1, y1 = x0 + cols * sq, y0 + rows * sq
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    world = corners @ board_R.T + board_t
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    mesh = mi.Mesh("board", 4, 2, has_vertex_texcoords=True)
    mp = mi.traverse(mesh)
    mp["vertex_positions"] = mi.Float((world * MM).ravel().astype(np.float32))
    mp["vertex_texcoords"] = mi.Float(uv.ravel().astype(np.float32))
    mp["faces"] = mi.UInt32(np.array([0, 1, 2, 0, 2, 3], np.uint32))
    mp.update()
    bmp = mi.Bitmap(tex)
    mesh_path = workdir / "board.ply"
    mesh.write_ply(str(mesh_path))
    d = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "camera": _camera_dict(spec),
        "board": {"type": "ply", "filename": str(mesh_path), "face_normals": True,
                  "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
                      "type": "bitmap", "bitmap": bmp, "filter_type": "nearest", "raw": True, "wrap_mode": "clamp"}}}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [radiance] * 3}},
    }
    return mi.load_dict(d)


def new_workdir() -> tempfile.TemporaryDirectory:
    return tempfile.TemporaryDirectory(prefix="glossrig-scene-")
