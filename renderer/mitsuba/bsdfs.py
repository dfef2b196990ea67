"""Our surface shading as a Mitsuba 3 BSDF plugin (`renderer_phong`), for the materials Mitsuba's own plugins
do not express: a Phong highlight (Mitsuba 3 has no Phong BSDF), and a diffuse weight other than 1 under
ambient light (Mitsuba's albedo AOV, which `export.develop` multiplies by the ambient intensity, would include
the weight; ours does not). Written in Python with Dr.Jit arithmetic like `renderer.mitsuba.sensors`.

The model is renderer/scene/materials.py's local term, lit by a light from direction l (cosine included, as in
every Mitsuba BSDF):
    f · cos = w · [kd · c/π + ks · (s + 2)/(2π) · max(0, r·v)^s] · max(0, n·l),   r = 2 (n·l) n − l,
with the albedo c (the `reflectance` texture, given as w · c), the weights kd (`diffuse`), ks (`specular`),
the exponent s (`shininess`) and w = 1 − reflect − transmit (`weight`). Two-sided: n faces the viewer v.
`eval_diffuse_reflectance` is w · c, so the ambient term is intensity · w · c as ours.

Properties: `reflectance` (texture: w · albedo), `weight`, `diffuse`, `specular`, `shininess` (floats).
Call `register(mi)` after choosing a variant (registration is per variant).
"""
from __future__ import annotations

import math

_REGISTERED: set = set()


def _class(mi):
    import drjit as dr

    class RendererPhong(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.reflectance = props.get_texture("reflectance")  # an rgb value becomes a uniform texture
            weight = props.get("weight", 1.0)
            self.kd_over_w = props.get("diffuse", 1.0) / math.pi  # the texture already holds the weight w
            self.ks = weight * props.get("specular", 0.0)
            self.s = props.get("shininess", 32.0)
            flags = (mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
                     | mi.BSDFFlags.BackSide)
            self.m_components = [flags]
            self.m_flags = flags

        @staticmethod
        def _facing(si, wo):
            """wi, wo in the local frame turned so that the normal faces the viewer (two-sided)."""
            flip = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
            return mi.Vector3f(si.wi.x, si.wi.y, si.wi.z * flip), mi.Vector3f(wo.x, wo.y, wo.z * flip)

        def eval(self, ctx, si, wo, active=True):
            wi, wo = self._facing(si, wo)
            cos_o = wo.z
            rv = dr.maximum(wo.z * wi.z - wo.x * wi.x - wo.y * wi.y, 0.0)  # (2 (n·l) n − l)·v
            lobe = dr.power(rv, self.s) if self.s > 0 else 1.0
            value = self.reflectance.eval(si, active) * self.kd_over_w + self.ks * (self.s + 2) / (2 * math.pi) * lobe
            return dr.select(active & (cos_o > 0) & (wi.z > 0), value * cos_o, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            _, wo = self._facing(si, wo)
            return dr.select(active & (wo.z > 0), mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            flip = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
            bs = mi.BSDFSample3f()
            bs.wo = mi.Vector3f(wo.x, wo.y, wo.z * flip)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = 0
            value = self.eval(ctx, si, bs.wo, active)
            return bs, dr.select(bs.pdf > 0, value / bs.pdf, 0.0)

        def eval_diffuse_reflectance(self, si, active=True):
            return self.reflectance.eval(si, active)

        def to_string(self):
            return f"RendererPhong[diffuse/π={self.kd_over_w}, specular={self.ks}, shininess={self.s}]"

    return RendererPhong


def register(mi) -> None:
    """Register `renderer_phong` with Mitsuba for its current variant (idempotent)."""
    variant = mi.variant()
    if variant in _REGISTERED:
        return
    cls = _class(mi)
    mi.register_bsdf("renderer_phong", lambda props: cls(props))
    _REGISTERED.add(variant)
