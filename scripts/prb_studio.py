"""The material studio set up for inverse rendering, shared by ``bench_prb_gradients.py`` and
``bench_inverse.py`` (both import it from this folder).

Bitmap textures load as 8-bit data, which has no derivatives: the ground's albedo is loaded
as floats (the bitmap's ``format`` ``variant``) and resampled to a small texture, the one
the optimisation recovers. The unknowns of the optimisation start from :data:`START`.
"""

from __future__ import annotations

import numpy as np

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import mitsuba as mi

#: Side of the ground's albedo texture (texels): few enough that each covers many pixels of a
#: small render (tiled 22 times over the ground, as the studio's own texture is).
TEXTURE_RES = 16
ROUGHNESS = "copper_ggx010.alpha.value"
PLASTIC_ROUGHNESS = "plastic_ball.bsdf.alpha"
TEXTURE = "ground.bsdf.reflectance.data"
#: Where the optimisation starts: the knot rougher than its 0.1, the ground a flat grey.
START = {ROUGHNESS: 0.3, TEXTURE: 0.35}
#: Integrators compared: name -> (plugin dict, the envmap's own mis_compensation).
METHODS = {
    "sh_prb": ({"type": "sh_prb"}, False),
    "prb": ({"type": "prb"}, False),
    "prb + mis_compensation": ({"type": "prb"}, True),
}


def load_studio(res: int, mis_compensation: bool = False) -> mi.Scene:
    """The material studio at ``res`` pixels wide with a float TEXTURE_RES^2 ground albedo."""
    from mitsuba_shsampling.scenes import SCENES_DIR, builtin_scenes, scene_parameters

    path = builtin_scenes()["material_studio"]
    with open(path) as f:
        text = f.read()
    tiles = '<string name="filename" value="textures/tiles.png"/>'
    assert tiles in text, "the studio's ground texture moved: update prb_studio.py"
    text = text.replace(tiles, tiles + '\n<string name="format" value="variant"/>')
    mi.Thread.thread().file_resolver().prepend(SCENES_DIR)
    declared = scene_parameters(path)
    height = max(1, round(res * int(declared["height"]) / int(declared["res"])))
    scene = mi.load_string(text, res=str(res), height=str(height),
                           mis_compensation="true" if mis_compensation else "false")
    params = mi.traverse(scene)
    full = params[TEXTURE].numpy()
    block = full.shape[0] // TEXTURE_RES
    params[TEXTURE] = mi.TensorXf(full.reshape(TEXTURE_RES, block, TEXTURE_RES, block, -1).mean(axis=(1, 3)))
    params.update()
    return scene


def envmap_keys(params: mi.SceneParameters) -> tuple[str, str]:
    """The keys of the (unnamed) envmap's ``scale`` and ``data`` in the scene's parameters."""
    keys = [k for k in params.keys() if params.properties[k][2].class_name() == "EnvironmentMapEmitter"]
    return next(k for k in keys if k.endswith(".scale")), next(k for k in keys if k.endswith(".data"))


def set_start(params: mi.SceneParameters) -> None:
    """Put the optimisation's unknowns at :data:`START`."""
    params[ROUGHNESS] = START[ROUGHNESS]
    params[TEXTURE] = mi.TensorXf(np.full((TEXTURE_RES, TEXTURE_RES, 3), START[TEXTURE], np.float32))
    params.update()


def render_target(res: int, spp: int = 4096) -> mi.TensorXf:
    """The image to match: the studio with its own parameters, rendered by ``path`` (in passes
    of at most 1024 spp). Its noise is part of what an optimisation fits: against a 512-spp
    target every method's texture error was 0.05-0.07 after 40 s (the optimisation of ``bench_inverse.py``'s
    ``roughness_texture`` task), against
    0.03-0.05 with 4096 spp."""
    scene = load_studio(res)
    path = mi.load_dict({"type": "path", "max_depth": 6})
    passes = max(1, spp // 1024)
    images = [np.array(mi.render(scene, integrator=path, spp=spp // passes, seed=k)) for k in range(passes)]
    return mi.TensorXf(np.mean(images, axis=0))
