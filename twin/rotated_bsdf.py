"""Any Mitsuba 3 BSDF turned about the normal with the sample: ``glossrig_rotated``.

A stock BSDF (``roughconductor``, ``principled``, ...) puts its anisotropy on the
shading frame's ``s`` axis (``alpha_u`` along ``s = dp/du``), and on the twin's
``cylinder`` ``s`` runs around the cylinder (``axis x normal``, thesis eq. 4.61).
The rig's sample rotation turns the sample's tangent about the normal (eq. 4.62,
counter-clockwise seen from outside), and a material is fixed to its sample, so its
frame must turn with it. No stock plugin turns the tangent frame (``normalmap``
changes the normal, the ``cylinder`` shape has no uv to rotate), so this wrapper does
it: it expresses ``si.wi`` and ``wo`` in the material's frame, the shading frame turned
by ``tangent_rotation`` (radians) about the normal, and calls the nested BSDF there;
sampled directions are turned back. A rotation about the normal leaves ``cos theta``
and solid angles unchanged, so values, pdfs and sample weights need no correction.
The convention is the one of ``glossrig_ward``'s ``tangent_rotation``
(:mod:`glossrig.twin.ward_bsdf`): the material's ``u`` axis is ``s`` turned by
``tangent_rotation``.

Parameters: ``bsdf`` (the nested BSDF) and ``tangent_rotation`` (float, radians;
traversable as ``tangent_rotation``, so a scene turns it with ``mi.traverse``).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from glossrig.twin.bsdf_plugin import PluginBSDF

PLUGIN = "glossrig_rotated"


class RotatedBSDF(PluginBSDF):
    PLUGIN = PLUGIN
    TRAVERSED = (("tangent_rotation", False),)

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        nested = [props[k] for k in props.keys() if isinstance(props[k], mi.BSDF)]
        if len(nested) != 1:
            raise ValueError(f"{PLUGIN} takes exactly one nested BSDF, got {len(nested)}")
        self.nested = nested[0]
        self.tangent_rotation = mi.Float(props["tangent_rotation"] if "tangent_rotation" in props else 0.0)
        self.m_components = [self.nested.flags(i) for i in range(self.nested.component_count())]
        self.m_flags = self.nested.flags()

    def _turn(self, v, sign):
        """``v`` from the shading frame into the material's frame (``sign`` = 1) or back (-1)."""
        c, s = dr.cos(self.tangent_rotation), sign * dr.sin(self.tangent_rotation)
        return mi.Vector3f(c * v.x + s * v.y, -s * v.x + c * v.y, v.z)

    def _si(self, si):
        si2 = mi.SurfaceInteraction3f(si)
        si2.wi = self._turn(si.wi, 1.0)
        return si2

    def eval(self, ctx, si, wo, active=True):
        return self.nested.eval(ctx, self._si(si), self._turn(wo, 1.0), active)

    def pdf(self, ctx, si, wo, active=True):
        return self.nested.pdf(ctx, self._si(si), self._turn(wo, 1.0), active)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.nested.eval_pdf(ctx, self._si(si), self._turn(wo, 1.0), active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs, weight = self.nested.sample(ctx, self._si(si), sample1, sample2, active)
        bs.wo = self._turn(bs.wo, -1.0)
        return bs, weight

    def eval_diffuse_reflectance(self, si, active=True):
        return self.nested.eval_diffuse_reflectance(self._si(si), active)

    def to_string(self):
        return f"RotatedBSDF[tangent_rotation={self.tangent_rotation}, nested={self.nested}]"


register = RotatedBSDF.register
