"""Renders of a fitted material for people to look at (issue 17; thesis figs. 6.2 and 7.4).

* :func:`environment_map` - a procedural studio environment (latitude-longitude,
  +y up, as Mitsuba 3's ``envmap`` emitter reads it): a sky-like gradient above the
  horizon, a dark floor below, and three soft bright "softboxes". Made from
  formulas, so nothing is downloaded and every render is reproducible.
* :func:`render_sphere` - a unit sphere of the material lit by that environment
  (thesis fig. 6.2 renders the fitted samples as spheres). The sphere is turned so
  that its pole axis is vertical in the image: Mitsuba's tangent ``dp/du`` of a
  sphere runs along the latitude circles, so the lobe's x axis (eq. 4.80,
  ``lobe_rotation`` = 0) runs horizontally around the sphere.
* :func:`render_cloth` - a draped cloth (thesis fig. 7.4 renders the fabricated
  anisotropic gloss on cloth): a subdivided plane displaced by a few sines, with
  analytic normals and UVs whose ``u`` runs along the weave (+x of the cloth).
  Mitsuba 3 builds a mesh's shading frame with ``s = dp/du`` (made orthogonal to
  the interpolated normal), so the anisotropic lobe orients along the weave.
* :func:`render_material_views` - both, as PNGs, for the report
  (:func:`glossrig.core.report.document.write_report` takes them as inputs, so
  ``glossrig.core`` stays free of Mitsuba, design.md).
* :func:`render_preview` and :func:`preview_scene` - the point-lit preview sphere
  of ``glossrig fit --plots`` (moved here from ``glossrig.core.fitting.fit_plots``, which
  must not import the twin; same names and arguments).

Materials are the ``glossrig_ward`` dicts of :func:`glossrig.core.fitting.export.mitsuba_material`
(or any Mitsuba BSDF dict). Images are written as 8-bit sRGB (IEC 61966-2-1) of
the linear radiance times ``exposure``, clipped at 1: one fixed exposure, so
renders of different materials compare.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError

#: (azimuth deg, elevation deg, angular radius deg, radiance) of the environment's softboxes
SOFTBOXES = ((-40.0, 35.0, 9.0, 40.0), (70.0, 50.0, 7.0, 25.0), (170.0, 20.0, 12.0, 12.0))


def _mi():
    try:
        from .mitsuba_env import mitsuba
        return mitsuba()
    except ImportError as e:
        raise InputError(f"Mitsuba (or the twin's Ward BSDF) is not available ({e})") from None


def environment_map(width: int = 512, *, sky=(0.55, 0.62, 0.75), horizon=(0.85, 0.85, 0.85),
                    floor=(0.12, 0.11, 0.10), softboxes=SOFTBOXES) -> np.ndarray:
    """Linear RGB radiance, float32 ``(width // 2, width, 3)``, latitude-longitude with
    row 0 at the zenith (+y) as Mitsuba's ``envmap`` reads it.

    Above the horizon the radiance blends from ``horizon`` to ``sky`` with the sine of
    the elevation; below it is ``floor`` (a grey studio floor, slightly lighter near the
    horizon). Each softbox is a disc of smooth edge (a raised-cosine falloff over its
    outer 30 %) at the given azimuth and elevation, of uniform radiance: the bright
    area lights a glossy lobe reflects. Only its shape is physical; the values are
    chosen to expose a dark glossy sheet (rho_d ~ 0.05) visibly at exposure 1."""
    w = int(width)
    if w < 8 or w % 2:
        raise InputError(f"environment map width must be an even number >= 8, got {width!r}")
    h = w // 2
    el = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi            # +pi/2 at row 0
    az = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    EL, AZ = np.meshgrid(el, az, indexing="ij")
    s = np.sin(EL)[..., None]
    img = np.where(s > 0, np.asarray(horizon) * (1 - s) + np.asarray(sky) * s,
                   np.asarray(floor) * (1 + 0.6 * (1 + s)))
    d = np.stack([np.cos(EL) * np.cos(AZ), np.sin(EL), np.cos(EL) * np.sin(AZ)], axis=-1)
    for a, e, r, L in softboxes:
        a, e, r = np.radians(a), np.radians(e), np.radians(r)
        c = np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])
        ang = np.arccos(np.clip(d @ c, -1, 1))
        edge = 0.3 * r
        k = np.clip((r - ang) / edge, 0, 1)
        img = img + (L * 0.5 * (1 - np.cos(np.pi * k)))[..., None]
    return img.astype(np.float32)


def write_environment_exr(path, width: int = 512) -> Path:
    """Save :func:`environment_map` as an OpenEXR file (through ``mi.Bitmap``)."""
    mi = _mi()
    path = Path(path)
    mi.Bitmap(environment_map(width)).write(str(path))
    return path


def _to_srgb8(img: np.ndarray, exposure: float) -> np.ndarray:
    x = np.clip(np.nan_to_num(np.asarray(img, np.float64)[..., :3] * exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)


def _render(mi, scene: dict, size: int, spp: int, seed: int) -> np.ndarray:
    try:
        return np.array(mi.render(mi.load_dict(scene), seed=seed, spp=spp), dtype=np.float64)[..., :3]
    except Exception as e:  # Mitsuba reports plugin/parameter problems as RuntimeError
        raise InputError(f"render failed: {e}") from None


def _check(size: int, spp: int) -> None:
    if int(size) < 8 or int(spp) < 1:
        raise InputError(f"render size must be >= 8 px and spp >= 1, got size={size!r}, spp={spp!r}")


def _sensor(mi, origin, target, size: int, spp: int, fov: float) -> dict:
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": int(size), "height": int(size), "rfilter": {"type": "gaussian"}},
            "sampler": {"type": "independent", "sample_count": int(spp)}}


def _env(mi, env_width: int) -> dict:
    return {"type": "envmap", "bitmap": mi.Bitmap(environment_map(env_width)), "scale": 1.0}


def sphere_scene(material: dict, size: int = 512, spp: int = 128, env_width: int = 512) -> dict:
    """Mitsuba scene dict of :func:`render_sphere`."""
    mi = _mi()
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 4},
            "sensor": _sensor(mi, [0, 0.9, 4.6], [0, 0, 0], size, spp, 30.0),
            "sphere": {"type": "sphere", "radius": 1.0, "bsdf": material,
                       # local +z (the pole Mitsuba's u runs around) -> world +y
                       "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)},
            "env": _env(mi, env_width)}


def render_sphere(material: dict, path, *, size: int = 512, spp: int = 128, seed: int = 0,
                  exposure: float = 1.0, env_width: int = 512) -> Path:
    """A sphere of ``material`` lit by :func:`environment_map`, written as an sRGB PNG."""
    from PIL import Image

    _check(size, spp)
    mi = _mi()
    img = _render(mi, sphere_scene(material, size, spp, env_width), size, spp, seed)
    path = Path(path)
    Image.fromarray(_to_srgb8(img, exposure)).save(path)
    return path


def cloth_height(x, y):
    """Height (z) of the cloth over the (x, y) square [-1, 1]^2, and its gradient.

    A few sines: two broad folds across the weave, one along it and a diagonal
    ripple - enough curvature for a lobe's highlight to trace the folds."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    terms = ((0.12, 1.3, 0.0, 0.4), (0.05, 2.7, 0.4, 1.3), (0.04, 0.0, 1.6, 0.2), (0.015, 3.5, 3.0, 2.0))
    z = np.zeros_like(x)
    gx = np.zeros_like(x)
    gy = np.zeros_like(x)
    for a, kx, ky, p in terms:
        arg = np.pi * (kx * x + ky * y) + p
        z += a * np.sin(arg)
        gx += a * np.pi * kx * np.cos(arg)
        gy += a * np.pi * ky * np.cos(arg)
    return z, gx, gy


def cloth_mesh_arrays(n: int = 160, weave_repeats: float = 1.0):
    """Vertices (V, 3), normals (V, 3), UVs (V, 2) and faces (F, 3) of the cloth.

    The cloth lies in the world's x-z plane with height along +y: world
    ``(x, h(x, y), -y)``. UV ``u`` grows along world +x (the weave), ``v`` along -z, so
    ``dp/du`` - the tangent of the shading frame and the lobe's x axis at
    ``lobe_rotation`` = 0 - runs along the weave."""
    n = int(n)
    if n < 2:
        raise InputError(f"cloth needs at least 2 vertices per side, got {n}")
    t = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(t, t, indexing="xy")
    Z, gx, gy = cloth_height(X, Y)
    pos = np.stack([X, Z, -Y], axis=-1).reshape(-1, 3)
    # surface (x, h, -y): tangents dP/dx = (1, gx, 0), dP/dy = (0, gy, -1); normal = dP/dy x dP/dx
    nrm = np.stack([-gx, np.ones_like(gx), -gy], axis=-1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = np.stack([(X + 1) / 2 * weave_repeats, (Y + 1) / 2 * weave_repeats], axis=-1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + 1, a + n, a + n + 1
    # wound so that cross(p1 - p0, p2 - p0) (Mitsuba's geometric normal) points up (+y), like the shading normals
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.uint32)
    return pos.astype(np.float32), nrm.astype(np.float32), uv.astype(np.float32), faces


def _cloth_mesh(mi, material: dict, n: int):
    pos, nrm, uv, faces = cloth_mesh_arrays(n)
    props = mi.Properties()
    # a cloth shows both sides where a fold turns it away from the camera
    props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": material})
    mesh = mi.Mesh("cloth", len(pos), len(faces), props=props, has_vertex_normals=True,
                   has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(pos.ravel())
    p["faces"] = mi.UInt32(faces.ravel())
    p["vertex_normals"] = mi.Float(nrm.ravel())
    p["vertex_texcoords"] = mi.Float(uv.ravel())
    p.update()
    return mesh


def cloth_scene(material: dict, size: int = 512, spp: int = 128, env_width: int = 512, n: int = 160) -> dict:
    """Mitsuba scene dict of :func:`render_cloth` (the mesh is built here)."""
    mi = _mi()
    try:
        mesh = _cloth_mesh(mi, material, n)
    except Exception as e:
        raise InputError(f"cloth mesh / material could not be built: {e}") from None
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 4},
            "sensor": _sensor(mi, [0.0, 2.2, 1.9], [0, -0.1, 0.05], size, spp, 42.0),
            "cloth": mesh, "env": _env(mi, env_width)}


def render_cloth(material: dict, path, *, size: int = 512, spp: int = 128, seed: int = 0,
                 exposure: float = 1.0, env_width: int = 512, n: int = 160) -> Path:
    """A draped cloth of ``material``, weave along the image's horizontal, lit by
    :func:`environment_map`; written as an sRGB PNG."""
    from PIL import Image

    _check(size, spp)
    mi = _mi()
    img = _render(mi, cloth_scene(material, size, spp, env_width, n), size, spp, seed)
    path = Path(path)
    Image.fromarray(_to_srgb8(img, exposure)).save(path)
    return path


def render_material_views(material: dict, out_dir, *, size: int = 512, spp: int = 128, seed: int = 0,
                          exposure: float = 1.0, prefix: str = "render") -> dict[str, Path]:
    """Sphere and cloth of ``material`` into ``out_dir`` (created): ``{"sphere": PNG,
    "cloth": PNG}``, the ``renders`` argument of :func:`glossrig.core.report.document.write_report`.
    ``size`` >= 512 px in real use (the issue's minimum); tests render tiny."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("render folder is a file", path=out)
    out.mkdir(parents=True, exist_ok=True)
    return {"sphere": render_sphere(material, out / f"{prefix}_sphere.png", size=size, spp=spp, seed=seed,
                                    exposure=exposure),
            "cloth": render_cloth(material, out / f"{prefix}_cloth.png", size=size, spp=spp, seed=seed,
                                  exposure=exposure)}


# ------------------------------------------------------- point-lit preview (glossrig fit --plots)

def preview_scene(material: dict, to_world, size: int = 160, spp: int = 64, key: float = 200.0,
                  env: float = 0.6) -> dict:
    """Mitsuba scene dict: a unit sphere of ``material`` lit by a point key light
    (intensity ``key``, W/sr) from the upper left and a uniform environment of
    radiance ``env``; camera at ``to_world``. The defaults expose a diffuse
    albedo of ~0.05 (the thesis's scratched sheets) as a visible dark grey; the
    exposure is fixed, so previews of different materials compare."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {
            "type": "perspective", "fov": 30,
            "to_world": to_world,
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "gaussian"}},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": material},
        "key": {"type": "point", "position": [-3.0, 3.0, 4.0], "intensity": {"type": "rgb", "value": [key] * 3}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [env] * 3}},
    }


def render_preview(material: dict, path, *, size: int = 160, spp: int = 64, seed: int = 0) -> Path:
    """Render a sphere of the fitted material (``glossrig.core.fitting.export`` dict)
    through the twin's ``glossrig_ward`` BSDF, lit by a point light, and write an
    sRGB PNG (``glossrig fit --plots``'s ``preview_sphere.png``).

    The sphere's tangent is Mitsuba's ``dp/du``, around its pole axis (+z, towards
    the camera here), so the anisotropic highlight stretches along or across the
    latitude circles according to ``lobe_rotation``. Raises :class:`InputError`
    when the twin's BSDF (or Mitsuba) is not available."""
    from PIL import Image

    mi = _mi()
    cam = mi.ScalarTransform4f().look_at(origin=[0, 0, 5.2], target=[0, 0, 0], up=[0, 1, 0])
    scene = preview_scene(material, cam, size, spp)
    try:
        img = np.array(mi.render(mi.load_dict(scene), seed=seed), dtype=np.float64)[..., :3]
    except Exception as e:  # Mitsuba reports plugin/parameter problems as RuntimeError
        raise InputError(f"preview render failed: {e}") from None
    path = Path(path)
    Image.fromarray(_to_srgb8(img, 1.0)).save(path)
    return path
