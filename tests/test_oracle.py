"""Specification of the oracle: exact tabulated product sampling as a reference row of ``compare``.

The oracle warp samples (1 - e) w(c) / W + e E(c) / E(root) over the N x N
cells of one pyramid level (w(c) = BSDF at the cell centre x the cell's exact
environment integral) and follows the environment inside the cell. Its samples
follow its pdf, its pdf covers every lit direction, ``oracle_direct`` renders
are unbiased with and without BSDF samples, and ``compare`` runs its rows only
on request, outside the verdict.
"""

import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba import chi2  # noqa: E402

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import sun_sky_latlong  # noqa: E402
from mitsuba_shsampling.grid import grid_direction  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.lobes.fit import luminance  # noqa: E402
from mitsuba_shsampling.report.methods import METHODS, available_methods, method_by_name  # noqa: E402
from mitsuba_shsampling.sweep import aggregate  # noqa: E402
from mitsuba_shsampling.warp.oracle import OracleWarp  # noqa: E402

from test_integrators import MATERIALS, assert_unbiased, make_scene  # noqa: E402
from leaf_chi2 import LeafAlignedChiSquareTest  # noqa: E402

#: Pyramid depth of the warp tests: chi2 bins can then sit inside single leaves.
DEPTH = 6
#: Table resolution of the warp tests (level 3: three environment-only levels below it).
RESOLUTION = 8
TILTED = mi.ScalarTransform4f().rotate((np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])).tolist(), 25.0)


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


@pytest.fixture(scope="module")
def sun_pyramid() -> EnvPyramid:
    """Sky plus a tiny (0.5 degree), 1e5 times brighter sun, under a tilted to_world."""
    return EnvPyramid.from_latlong(sun_sky_latlong(64, 128), to_world=TILTED, max_depth=DEPTH)


def shading_point(normal, wi_world, bsdf: dict):
    """f(world direction, active) = luminance of the BSDF value at one fixed shading point."""
    bsdf = mi.load_dict(bsdf)
    si = dr.zeros(mi.SurfaceInteraction3f)
    n = dr.normalize(mi.Vector3f(normal))
    si.n, si.sh_frame = n, mi.Frame3f(n)
    si.wi = si.to_local(dr.normalize(mi.Vector3f(wi_world)))
    ctx = mi.BSDFContext()
    return lambda d, active: luminance(bsdf.eval(ctx, si, si.to_local(d), active))


#: A glossy GGX lobe (its reflection close to the sun) and a diffuse one facing away from it.
LOBES = {
    "ggx_0.2": ((0.2, 0.9, 0.1), (-0.3, 0.5, 0.6), {"type": "roughconductor", "alpha": 0.2}),
    "diffuse": ((0.1, -0.9, 0.4), (0.0, -1.0, 0.0), {"type": "diffuse"}),
}


def leaf_centres(pyramid: EnvPyramid) -> mi.Vector3f:
    n = 1 << pyramid.depth
    iz, iphi = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    z = (-1 + (2 * iz.ravel() + 1) / n).astype(np.float32)
    phi = (2 * np.pi * (iphi.ravel() + 0.5) / n).astype(np.float32)
    return pyramid.world_from_grid(grid_direction(mi.Float(z), mi.Float(phi)))


@pytest.mark.parametrize("lobe", sorted(LOBES))
def test_chi2_oracle_samples_follow_the_oracle_pdf_at_a_shading_point(sun_pyramid, lobe):
    f = shading_point(*LOBES[lobe])
    warp = OracleWarp(sun_pyramid, RESOLUTION)
    table = warp.tabulate(f)
    # In the grid frame chi2's (cos theta, phi) bins nest inside the leaves, where
    # the pdf is bilinear (see tests/test_product.py:run_chi2 and tests/leaf_chi2.py).
    test = LeafAlignedChiSquareTest(
        domain=chi2.SphericalDomain(),
        sample_func=lambda u: sun_pyramid.grid_from_world(warp.sample(f, table, u)[0]),
        pdf_func=lambda d: warp.pdf(f, table, sun_pyramid.world_from_grid(d)),
        sample_dim=2, sample_count=400_000, res=2 << DEPTH, seed=5)
    assert test.run(0.01), test.messages


def test_sample_returns_the_pdf_that_pdf_evaluates_for_per_lane_shading_points(sun_pyramid):
    count = 1 << 12
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(3, count)).astype(np.float32)
    f = shading_point(mi.Vector3f(normals), mi.Vector3f(normals) + mi.Vector3f(0.3, 0.2, 0.1),
                      {"type": "roughconductor", "alpha": 0.1})
    warp = OracleWarp(sun_pyramid, RESOLUTION)
    table = warp.tabulate(f)
    d, pdf = warp.sample(f, table, mi.Point2f(rng.random((2, count)).astype(np.float32)))
    again = warp.pdf(f, table, d).numpy()
    pdf = pdf.numpy()
    assert np.all(pdf > 0) and np.max(np.abs(again - pdf) / pdf) <= 1e-4


@pytest.mark.parametrize("lobe", sorted(LOBES))
def test_pdf_integrates_to_one_and_covers_every_lit_leaf(sun_pyramid, lobe):
    warp = OracleWarp(sun_pyramid, RESOLUTION)
    f = shading_point(*LOBES[lobe])
    pdf = warp.pdf(f, warp.tabulate(f), leaf_centres(sun_pyramid)).numpy().astype(np.float64)
    leaves = sun_pyramid.level_numpy(sun_pyramid.depth).ravel().astype(np.float64)
    leaf_area = 4 * np.pi / leaves.size
    assert np.sum(pdf * leaf_area) == pytest.approx(1.0, abs=1e-5)
    # Coverage: never below the defensive share of the environment's own density.
    lit = leaves > 0
    env_pdf = leaves[lit] / sun_pyramid.total / leaf_area
    assert np.all(pdf[lit] >= (1 - 1e-4) * warp.defensive_share * env_pdf)


def test_a_lobe_without_light_samples_the_environment_alone(sun_pyramid):
    warp = OracleWarp(sun_pyramid, RESOLUTION)
    def dark(d, active):
        return mi.Float(0.0)
    table = warp.tabulate(dark)
    assert table.share.numpy()[0] == 1.0
    pdf = warp.pdf(dark, table, leaf_centres(sun_pyramid)).numpy()
    leaves = sun_pyramid.level_numpy(sun_pyramid.depth).ravel()
    np.testing.assert_allclose(pdf, leaves / sun_pyramid.total / (4 * np.pi / leaves.size), rtol=1e-4)


# ------------------------------------------------------------------ renders

#: Without BSDF samples a delta BSDF reflects nothing (as in ``direct``): ``smooth`` only with them.
ORACLE_MATERIALS = {k: MATERIALS[k] for k in ("ggx", "diffuse", "roughplastic", "blend")}


@pytest.mark.parametrize("samples, materials", [((1, 1), {**ORACLE_MATERIALS, "smooth": MATERIALS["smooth"]}),
                                                ((2, 0), ORACLE_MATERIALS)],
                         ids=["oracle_direct", "oracle_only"])
def test_oracle_renders_are_unbiased_against_path(samples, materials):
    scene = make_scene(rotated=True, materials=materials)
    emitter_samples, bsdf_samples = samples
    assert_unbiased(scene, mi.load_dict({"type": "oracle_direct", "resolution": 16,
                                         "emitter_samples": emitter_samples, "bsdf_samples": bsdf_samples}),
                    mi.load_dict({"type": "path", "max_depth": 2}))


def test_other_emitters_keep_mitsubas_sampling_beside_the_oracle():
    scene = make_scene(area_light=True, materials={k: MATERIALS[k] for k in ("ggx", "diffuse")})
    assert_unbiased(scene, mi.load_dict({"type": "oracle_direct", "resolution": 16}),
                    mi.load_dict({"type": "path", "max_depth": 2}))


def test_a_scene_without_environment_renders_what_direct_renders():
    scene = make_scene(environment=False, area_light=True, materials={"ggx": MATERIALS["ggx"]})
    assert_unbiased(scene, mi.load_dict({"type": "oracle_direct"}), mi.load_dict({"type": "direct"}))


# ------------------------------------------------------------ compare rows

def test_oracle_rows_exist_as_references_outside_the_default_method_set():
    rows = {m.name: m for m in METHODS if m.oracle}
    assert set(rows) == {"oracle_direct", "oracle_only"}
    assert rows["oracle_direct"].integrator == {"type": "oracle_direct", "emitter_samples": 1, "bsdf_samples": 1}
    assert rows["oracle_only"].integrator == {"type": "oracle_direct", "emitter_samples": 2, "bsdf_samples": 0}
    assert all("reference row" in m.label for m in rows.values())
    default, _ = available_methods(None)
    assert not set(rows) & {m.name for m in default}
    requested, notes = available_methods(["direct", "oracle_direct", "oracle_only"])
    assert [m.name for m in requested] == ["direct", "oracle_direct", "oracle_only"] and not notes
    assert method_by_name("oracle_only").oracle


def test_compare_runs_an_oracle_row_on_request_and_keeps_it_out_of_the_verdict(tmp_path):
    code = cli.main(["compare", scenes.builtin_scenes()["sphere_ggx010"], "--out", str(tmp_path),
                     "--res", "16", "--spp", "2", "--passes", "4", "--ref-spp", "32",
                     "--sampler", "independent", "--methods", "direct,sh_direct,oracle_only",
                     "--convergence-max-spp", "0", "--cache-dir", str(tmp_path / "cache"), "--no-progress"])
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    methods = report["scenes"][0]["runs"][0]["methods"]
    assert list(methods) == ["direct", "sh_direct", "oracle_only"]
    assert methods["oracle_only"]["oracle"] and not methods["sh_direct"]["oracle"]
    assert methods["oracle_only"]["equal_spp"]["error"]["mse"] > 0
    assert "oracle_only (reference row)" in (tmp_path / "index.html").read_text()
    (row,) = report["verdict"]
    for kind in ("equal_spp", "equal_time"):
        assert {row[kind]["numerator"], row[kind]["denominator"]} == {"sh_direct", "direct"}
        assert row[kind]["winner"] != "oracle_only"
    # At equal time an oracle renders 1 spp: what it costs, not a budget too coarse to compare.
    assert not any("oracle_only" in c for c in row["caveats"] if "equal-time spp" in c)


def test_a_sweep_never_names_an_oracle_row_its_winner():
    def entry(mse, oracle=False):
        e = {"error": {"mse": mse, "mse_per_pass": [mse, mse]}, "time_s": 1.0, "efficiency": 1 / mse}
        return {"equal_spp": e, "equal_time": e, "oracle": oracle}
    report = {"scenes": [{"notes": [], "runs": [{"methods": {
        "direct": entry(1.0), "sh_direct": entry(0.5), "oracle_only": entry(0.1, oracle=True)}}]}]}
    summary = aggregate.summarise_report(report)
    assert summary["winner"] == "sh_direct"
    assert summary["methods"]["oracle_only"]["mse_ratio_vs_best_mitsuba"] == pytest.approx(0.1)
