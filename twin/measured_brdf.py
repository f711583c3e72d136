"""Evaluate a measured RGL BRDF (``.bsdf``) at arbitrary direction pairs, in numpy.

The files of ../shared/data/rgl store the adaptive parameterisation of Dupuy &
Jakob, "An Adaptive Parameterization for Efficient Material Acquisition and
Rendering", ACM TOG (SIGGRAPH Asia) 2018. They are evaluated through Mitsuba's own
``measured`` plugin, the same code that renders them in the twin, so that the
ground truth of a study is exactly what the twin showed the rig.

Conventions: ``wi`` points to the light, ``wo`` to the camera, both unit vectors
``(..., 3)`` in the local frame (x = tangent, y = bitangent, z = normal) of
:mod:`glossrig.core.models.angles`. In the twin the plugin is queried with the camera
direction as Mitsuba's ``si.wi`` and the light as its ``wo``, and Mitsuba returns
f * cos(theta of its wo): :meth:`MeasuredBRDF.eval` does the same and divides the
cosine out, returning the BRDF f (1/sr) per RGB channel. Negative values, which the
plugin's RGB interpolation can give near grazing angles, are returned as they are
(the twin clamps radiance, not the BRDF; see twin/virtual_rig.py).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from glossrig.core.models.angles import local_direction
from glossrig.core.errors import InputError

LUMA = np.array([0.2126, 0.7152, 0.0722])    # Rec. 709, as the pipeline's luminance
CHUNK = 200_000


class MeasuredBRDF:
    """One RGL ``.bsdf`` file loaded through Mitsuba (:func:`twin.mitsuba_env.mitsuba`)."""

    def __init__(self, path):
        p = Path(path)
        if not p.is_file():
            raise InputError("measured BSDF file not found", path=p)
        from .mitsuba_env import mitsuba

        self.mi = mitsuba()
        self.path = p
        self.bsdf = self.mi.load_dict({"type": "measured", "filename": str(p.resolve())})

    def eval(self, wi, wo) -> np.ndarray:
        """RGB BRDF (..., 3) for light direction ``wi`` and camera direction ``wo``."""
        import drjit as dr

        mi = self.mi
        wi, wo = np.broadcast_arrays(np.asarray(wi, np.float64), np.asarray(wo, np.float64))
        shape = wi.shape[:-1]
        a, b = wi.reshape(-1, 3), wo.reshape(-1, 3)
        out = np.zeros((len(a), 3))
        ok = (a[:, 2] > 1e-6) & (b[:, 2] > 1e-6)
        idx = np.nonzero(ok)[0]
        ctx = mi.BSDFContext()
        for s in range(0, len(idx), CHUNK):
            j = idx[s:s + CHUNK]
            n = len(j)
            si = dr.zeros(mi.SurfaceInteraction3f, n)
            si.sh_frame = mi.Frame3f(mi.Normal3f(0, 0, 1))
            si.wi = mi.Vector3f(*(np.ascontiguousarray(b[j, k], np.float32) for k in range(3)))
            light = mi.Vector3f(*(np.ascontiguousarray(a[j, k], np.float32) for k in range(3)))
            v = np.array(self.bsdf.eval(ctx, si, light), dtype=np.float64).reshape(3, n).T
            out[j] = v / a[j, 2:3]
        return out.reshape(*shape, 3)

    def eval_angles(self, theta_in, phi_in, theta_out, phi_out) -> np.ndarray:
        """RGB BRDF at zenith/azimuth angles (radians) of the light and the camera."""
        return self.eval(local_direction(theta_in, phi_in), local_direction(theta_out, phi_out))

    def luminance(self, theta_in, phi_in, theta_out, phi_out) -> np.ndarray:
        """Rec. 709 luminance of :meth:`eval_angles` (the pipeline's ``y``)."""
        return self.eval_angles(theta_in, phi_in, theta_out, phi_out) @ LUMA

    def table(self, t) -> np.ndarray:
        """RGB BRDF at the angles of the rows of a samples table (``theta_in``, ``phi_in``, ...)."""
        return self.eval_angles(*(np.asarray(t[c], float) for c in ("theta_in", "phi_in", "theta_out", "phi_out")))
