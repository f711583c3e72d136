"""The extended Ward BRDF (thesis eq. 2.5, 4.79-4.80) as a Mitsuba 3 BSDF, ``glossrig_ward``.

Parameters (all RGB or float): ``rho_d``, ``rho_s``, ``alpha_x``, ``alpha_y``,
``lobe_rotation`` (radians, eq. 4.80) and ``tangent_rotation`` (radians): the
sample rotation of thesis 4.3.5. The tangent frame is the one of 4.3.5: Mitsuba's
shading frame on the ``cylinder`` shape has ``s = dp/du``, which runs around the
cylinder, i.e. ``s = axis x normal`` (eq. 4.61); the sample rotation turns it
about the normal (eq. 4.62). The formula is glossrig's one Ward evaluation,
:func:`glossrig.core.models.ward.ward_parts`, written in Dr.Jit (the lobe's slopes
``hx / hz, hy / hz`` in the lobe's axes, the exponent capped at
:data:`glossrig.core.models.ward.EXPONENT_CAP`); :func:`glossrig.core.models.ward.ward_local` is
its numpy reference in the tests. The one departure: the normalisation
``1 / sqrt(cos th_i cos th_o)`` is guarded by ``max(., 1e-12)``, since in single
precision the product of two grazing cosines can underflow to 0 (core's double
precision evaluation needs no guard above the horizon).

Sampling: a one-sample mixture of cosine-weighted diffuse sampling and Ward's
half-vector sampling (Walter, "Notes on the Ward BRDF", 2005), chosen with
probability proportional to rho_s / (rho_d + rho_s) (clamped to [0.1, 0.9]).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from glossrig.core.models.ward import EXPONENT_CAP
from glossrig.twin.bsdf_plugin import PluginBSDF

PLUGIN = "glossrig_ward"


class WardBSDF(PluginBSDF):
    PLUGIN = PLUGIN
    TRAVERSED = (("rho_d", True), ("rho_s", True), ("alpha_x", True), ("alpha_y", True), ("lobe_rotation", False),
                 ("tangent_rotation", False))

    def __init__(self, props):
        mi.BSDF.__init__(self, props)

        def read(name, default):
            return mi.Color3f(props[name]) if name in props else mi.Color3f(default)

        self.rho_d = read("rho_d", 0.5)
        self.rho_s = read("rho_s", 0.0)
        self.alpha_x = mi.Float(props["alpha_x"] if "alpha_x" in props else 0.1)
        self.alpha_y = mi.Float(props["alpha_y"] if "alpha_y" in props else 0.1)
        self.lobe_rotation = mi.Float(props["lobe_rotation"] if "lobe_rotation" in props else 0.0)
        self.tangent_rotation = mi.Float(props["tangent_rotation"] if "tangent_rotation" in props else 0.0)
        flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide \
            | mi.BSDFFlags.Anisotropic
        self.m_components = [mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide,
                             mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.Anisotropic]
        self.m_flags = flags

    # Frame: rotate Mitsuba's local (s, t, n) coordinates into the lobe's axes.
    # The sample's tangent is s turned by tangent_rotation; the lobe's x axis is
    # that tangent turned by -lobe_rotation (eq. 4.80 adds lobe_rotation to phi_h).
    def _lobe_xy(self, h):
        ang = self.tangent_rotation - self.lobe_rotation
        c, s = dr.cos(ang), dr.sin(ang)
        return c * h.x + s * h.y, -s * h.x + c * h.y

    def _from_lobe_xy(self, x, y):
        ang = self.tangent_rotation - self.lobe_rotation
        c, s = dr.cos(ang), dr.sin(ang)
        return c * x - s * y, s * x + c * y

    def _spec(self, wi, wo):
        h = dr.normalize(wi + wo)
        hx, hy = self._lobe_xy(h)
        e = -dr.minimum((dr.square(hx / self.alpha_x) + dr.square(hy / self.alpha_y)) / dr.square(h.z), EXPONENT_CAP)
        denom = 4.0 * dr.pi * self.alpha_x * self.alpha_y * dr.sqrt(dr.maximum(wi.z * wo.z, 1e-12))
        return dr.exp(e) / denom, h

    def _p_spec(self):
        a = dr.mean(self.rho_s)
        b = dr.mean(self.rho_d)
        return dr.clip(a / dr.maximum(a + b, 1e-9), 0.1, 0.9)

    def _pdf_spec(self, wi, wo):
        h = dr.normalize(wi + wo)
        hx, hy = self._lobe_xy(h)
        e = -(dr.square(hx / self.alpha_x) + dr.square(hy / self.alpha_y)) / dr.square(h.z)
        ph = dr.exp(e) / (dr.pi * self.alpha_x * self.alpha_y * h.z * h.z * h.z)
        return ph / (4.0 * dr.maximum(dr.dot(h, wo), 1e-9))

    def eval(self, ctx, si, wo, active=True):
        wi = si.wi
        ok = active & (wi.z > 0) & (wo.z > 0)
        spec, _ = self._spec(wi, wo)
        f = self.rho_d * dr.inv_pi + self.rho_s * spec
        return dr.select(ok, f * wo.z, mi.Color3f(0.0))

    def pdf(self, ctx, si, wo, active=True):
        wi = si.wi
        ok = active & (wi.z > 0) & (wo.z > 0)
        ps = self._p_spec()
        p = (1 - ps) * wo.z * dr.inv_pi + ps * self._pdf_spec(wi, wo)
        return dr.select(ok, p, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        wi = si.wi
        ps = self._p_spec()
        choose_spec = sample1 < ps
        # Diffuse: cosine-weighted hemisphere.
        wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
        # Specular: Walter 2005, eq. for anisotropic Ward half-vector sampling.
        u1, u2 = sample2.x, sample2.y
        phi = dr.atan2(self.alpha_y * dr.sin(2 * dr.pi * u2), self.alpha_x * dr.cos(2 * dr.pi * u2))
        cphi, sphi = dr.cos(phi), dr.sin(phi)
        tan2 = -dr.log(dr.maximum(1 - u1, 1e-12)) / (dr.square(cphi / self.alpha_x) + dr.square(sphi / self.alpha_y))
        cos_t = dr.rsqrt(1 + tan2)
        sin_t = dr.sqrt(dr.maximum(0.0, 1 - cos_t * cos_t))
        lx, ly = self._from_lobe_xy(sin_t * cphi, sin_t * sphi)
        h = mi.Vector3f(lx, ly, cos_t)
        wo_s = 2 * dr.dot(wi, h) * h - wi
        wo = dr.select(choose_spec, wo_s, wo_d)
        bs = mi.BSDFSample3f()
        bs.wo = wo
        bs.eta = 1.0
        bs.sampled_component = dr.select(choose_spec, mi.UInt32(1), mi.UInt32(0))
        bs.sampled_type = dr.select(choose_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        value, pdf = self.eval_pdf(ctx, si, wo, active)
        bs.pdf = pdf
        ok = active & (wi.z > 0) & (wo.z > 0) & (pdf > 0)
        return bs, dr.select(ok, value / dr.maximum(pdf, 1e-12), mi.Color3f(0.0))

    def to_string(self):
        return f"WardBSDF[rho_d={self.rho_d}, rho_s={self.rho_s}, alpha=({self.alpha_x}, {self.alpha_y})]"


register = WardBSDF.register
