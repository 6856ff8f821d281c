"""Reproducer of the abort that keeps the evaluated-sky sampling off ``main`` (issue 48).

Two scenes lit by Mitsuba's ``sunsky`` alive in one process, each built by ``sh_direct``
(whose set-up evaluates the emitter in kernels of its own), then rendered with enough
passes: the LLVM backend aborts the process with "invalid redefinition of function
'func_...'" (the ``Emitter::eval`` callable emitted several times into one kernel). With
the environment strategies too (no product code in the kernel); not when the first
scene is freed before the second is built; not without the evaluation kernels.

    python3 scripts/repro_two_sunsky_scenes_abort.py
"""
import sys

sys.path.insert(0, "tests")
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")
import test_skies as T  # noqa: E402
from test_integrators import assert_unbiased  # noqa: E402

from mitsuba_shsampling.integrators import register  # noqa: E402

register()
# Each scene replaces the one before while that one's integrator still holds it: the old
# sunsky is freed after the new one was built and evaluated. (Holding every scene, or
# freeing the old ones first, did not abort.)
for sky, integrator in ((T.LOW_SUN, {"type": "sh_direct", "max_bands": 5, "strategy": "environment_only"}),
                        (T.HIGH_SUN, {"type": "sh_direct", "max_bands": 5, "strategy": "environment"})):
    scene = T.make_scene(environment=sky, materials=T.SKY_MATERIALS)
    sh = mi.load_dict(integrator)
    env = sh.scenes.get(scene)
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}), spp=32, passes=16)
    print("rendered", sky["sun_direction"], flush=True)
