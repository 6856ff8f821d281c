"""The shading normals of frame-perturbing wrappers (``bumpmap``, ``normalmap``), per lane.

A wrapper hands its nested BSDF a shading frame of its own at every point: a
normal read from a texture (``normalmap``) or from a height field's gradient
(``bumpmap``). The nested BSDF's lobe is oriented about that normal, so the
product strategy orients the nested BSDF's fitted lobe about it too
(:class:`~mitsuba_shsampling.lobes.scene_lobes.SceneLobes`).

The normal is given in the local coordinates of ``si.sh_frame`` (the unperturbed
shading frame, z up). It only steers the product sampler: the sampler's pdf is
exact for any lobe (:mod:`~mitsuba_shsampling.warp.hierarchy`), and the MIS
weights and the estimate use the wrapper's own ``eval``/``pdf``. A normal that
differs from Mitsuba's (another Mitsuba version, a rule at the horizon) costs
variance, never bias; that is why the rules below are this module's own:

- a normal facing away from the viewer's side of the surface has its tangential
  part mirrored, so that the lobe stays on the side the viewer is on (Mitsuba's
  ``normalmap`` does the same with ``flip_invalid_normals``);
- where the normal is not finite (a mesh without uv derivatives), decodes to
  a vector shorter than :data:`MIN_NORMAL_LENGTH` (a normal map's mid-grey
  texel) or points below the unperturbed tangent plane, the unperturbed normal
  is used.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

FRAME_WRAPPERS = ("BumpMap", "NormalMap")
"""BSDF classes that perturb the shading frame per point."""

MIN_NORMAL_LENGTH = 1e-3
"""A decoded normal-map vector shorter than this has no direction to speak of."""


def nested_objects(obj) -> dict:
    """The objects (BSDFs, textures) a Mitsuba object holds, by the name under which
    it traverses them (``nested_bsdf``, ``nested_texture``, ``normalmap``...)."""
    found = {}

    class Collect(mi.TraversalCallback):
        def put(self, name, value, flags, *rest):
            if isinstance(value, (mi.BSDF, mi.Texture)):
                found[name] = value

    obj.traverse(Collect())
    return found


def nested_bsdf(wrapper: mi.BSDF) -> mi.BSDF | None:
    """The BSDF a frame-perturbing wrapper shades with (None if it cannot be found)."""
    return nested_objects(wrapper).get("nested_bsdf")


class PerturbedNormal:
    """The perturbed normal of one wrapper instance.

    Parameter ``wrapper`` (mi.BSDF): a ``bumpmap`` or a ``normalmap``; its
    texture and (bump) scale are read once, here.
    """

    def __init__(self, wrapper: mi.BSDF):
        kind = wrapper.class_name()
        if kind not in FRAME_WRAPPERS:
            raise ValueError(f"{kind} does not perturb the shading frame (expected one of {FRAME_WRAPPERS})")
        nested = nested_objects(wrapper)
        self.kind = kind
        self.texture = nested.get("nested_texture" if kind == "BumpMap" else "normalmap")
        if self.texture is None:
            raise ValueError(f"{kind} '{wrapper.id()}': its texture could not be found")
        self.scale = float(mi.traverse(wrapper)["scale"]) if kind == "BumpMap" else 1.0

    def local_normal(self, si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Vector3f:
        """The perturbed normal in ``si.sh_frame``'s local coordinates (unit length)."""
        if self.kind == "NormalMap":
            # The texture stores the normal in the shading frame, mapped from [-1, 1] to [0, 1].
            n = dr.fma(mi.Vector3f(self.texture.eval_3(si, active)), 2.0, -1.0)
            # A texel of (0.5, 0.5, 0.5) decodes to a vector of rounding noise.
            degenerate = dr.squared_norm(n) < MIN_NORMAL_LENGTH**2
        else:
            # The height field h(u, v) moves the surface along the shading normal:
            # dp/du + n (dh/du - n . dp/du), and likewise for v; the new normal is their cross product.
            grad = self.scale * self.texture.eval_1_grad(si, active)
            n_world = si.sh_frame.n
            dp_du = dr.fma(n_world, grad.x - dr.dot(n_world, si.dp_du), si.dp_du)
            dp_dv = dr.fma(n_world, grad.y - dr.dot(n_world, si.dp_dv), si.dp_dv)
            bumped = dr.cross(dp_du, dp_dv)
            bumped = dr.select(dr.dot(bumped, n_world) < 0, -bumped, bumped)
            n = si.sh_frame.to_local(bumped)
            degenerate = mi.Bool(False)  # a zero cross product is caught below, as NaN
        n = dr.normalize(n)
        away = si.wi.z * dr.dot(n, si.wi) <= 0
        n = dr.select(away, mi.Vector3f(-n.x, -n.y, n.z), n)
        usable = ~degenerate & dr.isfinite(n.x) & dr.isfinite(n.y) & dr.isfinite(n.z) & (n.z > 0)
        return dr.select(usable, n, mi.Vector3f(0.0, 0.0, 1.0))
