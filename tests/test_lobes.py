"""Specification of the per-BSDF SH lobe proxies (``mitsuba_shsampling.lobes``).

Tolerances: the proxy is a two-lobe model, so its *shape* is only checked
loosely (mean direction within 10 degrees and mean cosine within 0.2 of the
BSDF's for views above 30 degrees elevation,
where the mirror-axis Phong lobe does not spill far below the horizon); its *energy* must match the
BSDF's directional albedo within 2 % everywhere, grazing views included.
"""

import math
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.lobes import SceneLobes, bands_for_exponent  # noqa: E402
from mitsuba_shsampling.lobes.fit import luminance  # noqa: E402
from mitsuba_shsampling.sh.basis import sh_eval  # noqa: E402

REQUIRED_BSDFS = {
    "diffuse": {"type": "diffuse", "reflectance": 0.6},
    "roughconductor_ggx": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1},
    "roughconductor_beckmann": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.3},
    "roughplastic_ggx": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.15},
    "roughplastic_beckmann": {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.3},
    "principled": {"type": "principled", "roughness": 0.4, "metallic": 0.5},
    "twosided": {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.2}},
    "blendbsdf": {"type": "blendbsdf", "weight": 0.4, "bsdf_0": {"type": "diffuse"},
                  "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.15}},
}


def identity(v):
    return v


def rotated_grid_frame(v):
    """A grid frame that is not the world frame (the envmap convention with
    to_world = identity: z_g = y, x_g = -z, y_g = -x)."""
    return mi.Vector3f(-v.z, -v.x, v.y)


def plane_scene(bsdf: dict) -> mi.Scene:
    return mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": dict(bsdf)}})


def hit_plane(scene: mi.Scene, view_cosines, from_below=False) -> mi.SurfaceInteraction3f:
    """Intersections with the z = 0 rectangle at the origin, seen from the given
    view elevations (view direction in the x-z plane)."""
    c = np.asarray(view_cosines, dtype=np.float64)
    sign = -1.0 if from_below else 1.0
    d = np.stack([np.sqrt(1 - c * c), 0 * c, sign * c], -1)
    ray = mi.Ray3f(mi.Point3f(*(2 * d.T)), mi.Vector3f(*(-d.T)))
    return scene.ray_intersect(ray)


def reference_moments(bsdf: mi.BSDF, view_cosine: float, n: int = 300):
    """Energy and mean direction of g = eval (cosine included) by a midpoint rule in
    (z, phi) on the upper hemisphere (equal-area, weight dz dphi)."""
    z = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) * math.pi / n
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    st = np.sqrt(1 - zz * zz)
    d = np.stack([st * np.cos(pp), st * np.sin(pp), zz], -1).reshape(-1, 3)
    weight = (1 / n) * (math.pi / n)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    si.wi = mi.Vector3f(math.sqrt(1 - view_cosine ** 2), 0, view_cosine)
    g = np.array(luminance(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*d.T))), dtype=np.float64)
    energy = g.sum() * weight
    return energy, (g[:, None] * d).sum(0) * weight / energy


def to_numpy(values) -> np.ndarray:
    """List of Dr.Jit arrays -> array (len, lanes); one kernel for the whole list."""
    dr.eval(values)
    return np.array([np.array(v) for v in values])


def sphere_quadrature(n_theta=128, n_phi=256):
    """Gauss-Legendre in z x midpoint in phi over the whole sphere: (dirs (M,3), weights (M,))."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    zz, pp = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - zz * zz)
    d = np.stack([st * np.cos(pp), st * np.sin(pp), zz], -1).reshape(-1, 3)
    return d, np.repeat(w[:, None], n_phi, 1).reshape(-1) * (2 * math.pi / n_phi)


# -- The proxy matches quadrature of the BSDF's own eval ----------------------

@pytest.mark.parametrize("name", list(REQUIRED_BSDFS))
def test_proxy_energy_and_mean_direction_match_quadrature_of_bsdf_eval(name):
    scene = plane_scene(REQUIRED_BSDFS[name])
    lobes = SceneLobes(scene)
    bsdf = scene.shapes()[0].bsdf()
    view_cosines = [0.1, 0.35, 0.6, 0.95]
    w_d, w_g, s, valid = (np.array(v) for v in lobes.lookup(hit_plane(scene, view_cosines)))
    assert valid.all()
    for k, c in enumerate(view_cosines):
        energy, mean = reference_moments(bsdf, c)
        assert w_d[k] + w_g[k] == pytest.approx(energy, rel=0.02), f"energy at cos {c}"
        if c < 0.5:
            continue  # near the horizon only the energy is meaningful (see module docstring)
        normal = np.array([0.0, 0.0, 1.0])
        mirror = np.array([-math.sqrt(1 - c * c), 0.0, c])
        # Mean vector of the proxy: 2/3 n for cos/pi, (s+1)/(s+2) r for Phong_s.
        proxy_mean = (w_d[k] * 2 / 3 * normal + w_g[k] * (s[k] + 1) / (s[k] + 2) * mirror) \
            / (w_d[k] + w_g[k])
        cos_angle = proxy_mean @ mean / np.linalg.norm(proxy_mean) / np.linalg.norm(mean)
        assert math.degrees(math.acos(min(cos_angle, 1.0))) < 10.0, f"direction at cos {c}"
        assert np.linalg.norm(proxy_mean) == pytest.approx(np.linalg.norm(mean), abs=0.2), \
            f"spread at cos {c}"


def test_twosided_lobe_is_fitted_on_the_back_side_too():
    scene = plane_scene(REQUIRED_BSDFS["twosided"])
    lobes = SceneLobes(scene)
    front = [np.array(v) for v in lobes.lookup(hit_plane(scene, [0.5]))]
    back = [np.array(v) for v in lobes.lookup(hit_plane(scene, [0.5], from_below=True))]
    assert back[3].all()
    for f, b in zip(front[:3], back[:3]):
        assert b == pytest.approx(f, rel=1e-3)


def test_one_sided_bsdf_seen_from_below_skips_product_sampling():
    scene = plane_scene(REQUIRED_BSDFS["roughconductor_ggx"])
    lobes = SceneLobes(scene)
    coeffs, use_product = lobes.coefficients(hit_plane(scene, [0.5], from_below=True), identity)
    assert not np.array(use_product).any()
    assert (to_numpy(coeffs) == 0).all()


@pytest.mark.parametrize("name", ["roughconductor_beckmann", "blendbsdf"])
def test_sh_coefficients_match_quadrature_projection_of_proxy(name):
    scene = plane_scene(REQUIRED_BSDFS[name])
    lobes = SceneLobes(scene)
    si = hit_plane(scene, [0.7])
    coeffs, use_product = lobes.coefficients(si, rotated_grid_frame)
    w_d, w_g, s, _ = (float(np.array(v)[0]) for v in lobes.lookup(si))
    assert np.array(use_product)[0]

    # The proxy as a function, in the grid frame.
    c = 0.7
    normal = np.array(rotated_grid_frame(mi.Vector3f(0, 0, 1))).ravel()
    mirror = np.array(rotated_grid_frame(mi.Vector3f(-math.sqrt(1 - c * c), 0, c))).ravel()
    dirs, weights = sphere_quadrature()
    diffuse = w_d * np.maximum(dirs @ normal, 0) / math.pi
    glossy = w_g * (s + 1) / (2 * math.pi) * np.maximum(dirs @ mirror, 0) ** s
    basis = to_numpy(sh_eval(mi.Vector3f(*dirs.T), lobes.n_bands - 1))
    expected = basis @ (glossy * weights)
    # The diffuse part is band-limited to 3 bands (9 coefficients) by design.
    expected[:9] += basis[:9] @ (diffuse * weights)

    got = to_numpy(coeffs)[:, 0]
    assert len(got) == lobes.n_bands ** 2
    assert got[0] * math.sqrt(4 * math.pi) == pytest.approx(w_d + w_g, rel=1e-4)
    np.testing.assert_allclose(got, expected, atol=2e-3 * abs(expected).max())


# -- Which lanes use product sampling ------------------------------------------

@pytest.mark.parametrize("bsdf", [{"type": "conductor"}, {"type": "dielectric"},
                                  {"type": "thindielectric"}, {"type": "null"}])
def test_delta_bsdfs_give_use_product_false_without_warning(bsdf):
    scene = plane_scene(bsdf)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lobes = SceneLobes(scene)
    assert not lobes.has_product_lobes and lobes.n_bands == 0
    coeffs, use_product = lobes.coefficients(hit_plane(scene, [0.5, 0.9]), identity)
    assert coeffs == [] and not np.array(use_product).any()


@pytest.mark.parametrize("bsdf", [
    {"type": "roughdielectric", "alpha": 0.2},
    {"type": "roughdielectric", "alpha_u": 0.1, "alpha_v": 0.3},
])
def test_transmissive_bsdfs_warn_once_and_give_use_product_false(bsdf):
    scene = mi.load_dict({
        "type": "scene",
        "a": {"type": "rectangle", "bsdf": dict(bsdf, id="odd")},
        "b": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([5, 0, 0]),
              "bsdf": {"type": "ref", "id": "odd"}},
        "c": {"type": "sphere", "center": [0, 5, 0], "bsdf": {"type": "diffuse"}},
    })
    with pytest.warns(UserWarning, match="odd") as record:
        lobes = SceneLobes(scene)
    assert len([w for w in record if "odd" in str(w.message)]) == 1
    _, use_product = lobes.coefficients(hit_plane(scene, [0.4, 0.8]), identity)
    assert not np.array(use_product).any()
    assert lobes.has_product_lobes  # the diffuse sphere still has a lobe


def fitted_exponent(bsdf: dict, view_node: int = 8) -> float:
    scene = mi.load_dict({"type": "scene", "a": {"type": "rectangle", "bsdf": dict(bsdf, id="m")}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an anisotropic lobe is supported: no warning
        lobes = SceneLobes(scene)
    return float(lobes.fits["m"][0, view_node, 2])


@pytest.mark.parametrize("bsdf", [
    {"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.3},
    {"type": "principled", "roughness": 0.3, "anisotropic": 0.7},
])
def test_anisotropic_lobes_get_a_product_lobe(bsdf):
    scene = plane_scene(bsdf)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lobes = SceneLobes(scene)
    _, use_product = lobes.coefficients(hit_plane(scene, [0.4, 0.8]), identity)
    assert np.array(use_product).all()


def test_an_anisotropic_lobes_proxy_is_the_view_azimuth_average_between_its_two_roughnesses():
    sharp = fitted_exponent({"type": "roughconductor", "alpha": 0.1})
    wide = fitted_exponent({"type": "roughconductor", "alpha": 0.3})
    assert wide < fitted_exponent({"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.3}) < sharp


def test_per_lane_bsdf_identification_gives_each_spheres_row():
    names = ["diffuse", "roughconductor_ggx", "roughplastic_beckmann", "principled"]
    scene_dict = {"type": "scene"}
    for i, name in enumerate(names):
        scene_dict["sphere_" + name] = {"type": "sphere", "center": [3.0 * i, 0, 0],
                            "bsdf": dict(REQUIRED_BSDFS[name], id=name)}
    scene_dict["sphere_conductor"] = {"type": "sphere", "center": [12.0, 0, 0],
                               "bsdf": {"type": "conductor", "id": "conductor"}}
    scene_dict["sphere_second_diffuse"] = {"type": "sphere", "center": [15.0, 0, 0],
                                    "bsdf": {"type": "ref", "id": "diffuse"}}
    scene = mi.load_dict(scene_dict)
    lobes = SceneLobes(scene)

    # One ray per sphere (hitting at various view elevations), one miss.
    centers = np.array([0.0, 3.0, 6.0, 9.0, 12.0, 15.0, 40.0])
    offsets = np.array([0.1, 0.5, 0.7, 0.3, 0.2, 0.6, 0.0])
    ray = mi.Ray3f(mi.Point3f(centers + offsets, 0.0, 5.0), mi.Vector3f(0.0, 0.0, -1.0))
    si = scene.ray_intersect(ray)
    w_d, w_g, s, valid = (np.array(v) for v in lobes.lookup(si))
    view_cos = np.array(si.wi.z)

    expected_rows = names + [None, "diffuse", None]
    for lane, name in enumerate(expected_rows):
        if name is None:
            assert not valid[lane]
            continue
        assert valid[lane]
        params = lobes.fits[name][0]  # front side, (view node, [w_d, w_g, s])
        energy = np.interp(view_cos[lane], lobes.view_cosines, params[:, 0] + params[:, 1])
        assert w_d[lane] + w_g[lane] == pytest.approx(energy, rel=1e-4), name
        glossy = np.interp(view_cos[lane], lobes.view_cosines, params[:, 1])
        assert w_g[lane] == pytest.approx(glossy, rel=1e-3, abs=1e-5), name


# -- Band count ----------------------------------------------------------------

def test_band_count_grows_with_sharpness_and_respects_max_bands():
    bands = []
    for alpha in [0.6, 0.3, 0.15]:
        scene = plane_scene({"type": "roughconductor", "distribution": "ggx", "alpha": alpha})
        bands.append(SceneLobes(scene, max_bands=30).n_bands)
    assert bands[0] < bands[1] < bands[2] <= 30
    capped = SceneLobes(plane_scene({"type": "roughconductor", "alpha": 0.15}), max_bands=8)
    assert capped.n_bands == 8
    assert bands_for_exponent(capped.max_exponent) <= 8
    assert [bands_for_exponent(s) for s in [1, 10, 50, 200]] == sorted(
        bands_for_exponent(s) for s in [1, 10, 50, 200])


def test_diffuse_only_scene_uses_at_most_three_bands():
    lobes = SceneLobes(plane_scene({"type": "diffuse"}))
    assert lobes.has_product_lobes and 1 <= lobes.n_bands <= 3


def test_invalid_max_bands_raises():
    with pytest.raises(ValueError):
        SceneLobes(plane_scene({"type": "diffuse"}), max_bands=2)


# -- Robustness ------------------------------------------------------------------

def test_coefficients_are_finite_for_grazing_views_and_normals_at_the_poles():
    scene = mi.load_dict({
        "type": "scene",
        "sphere": {"type": "sphere", "bsdf": dict(REQUIRED_BSDFS["roughplastic_ggx"])},
    })
    lobes = SceneLobes(scene)
    # Rays down the z axis hit the pole (normal exactly +z, the grid frame's
    # pole for `identity`); rays offset to x ~ 1 hit at grazing view angles.
    x = np.array([0.0, 0.0, 0.999, 0.99999, 1 - 1e-7, 0.5])
    y = np.zeros_like(x)
    ray = mi.Ray3f(mi.Point3f(x, y, 5.0), mi.Vector3f(0.0, 0.0, -1.0))
    si = scene.ray_intersect(ray)
    for frame in (identity, rotated_grid_frame):
        coeffs, use_product = lobes.coefficients(si, frame)
        values = to_numpy(coeffs)
        assert np.isfinite(values).all()
        assert np.array(use_product)[[0, 1, 5]].all()
    # Normal along the rotated grid frame's pole: the sphere's point at +y.
    ray = mi.Ray3f(mi.Point3f(0.0, 5.0, 0.0), mi.Vector3f(0.0, -1.0, 0.0))
    coeffs, use_product = lobes.coefficients(scene.ray_intersect(ray), rotated_grid_frame)
    assert np.isfinite(to_numpy(coeffs)).all() and np.array(use_product).all()


def test_coefficients_trace_into_one_kernel_with_per_lane_bsdfs():
    """The per-lane path is traceable: evaluating all coefficients at once is one
    launch (no host round trip inside `coefficients`)."""
    scene = mi.load_dict({
        "type": "scene",
        "a": {"type": "sphere", "center": [0, 0, 0], "bsdf": REQUIRED_BSDFS["principled"]},
        "b": {"type": "sphere", "center": [3, 0, 0], "bsdf": REQUIRED_BSDFS["roughconductor_ggx"]},
    })
    lobes = SceneLobes(scene)
    ray = mi.Ray3f(mi.Point3f(mi.Float([0.2, 3.4]), 0.0, 5.0), mi.Vector3f(0.0, 0.0, -1.0))
    si = scene.ray_intersect(ray)
    dr.eval(si)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        coeffs, use_product = lobes.coefficients(si, rotated_grid_frame)
        dr.eval(coeffs, use_product)
        launches = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    assert len(launches) == 1


def whole_grid_fit(g, quadrature, fit):
    """The fit written out in numpy: the whole coarse grid weighed on every node where the lobe
    is positive (float32 terms, as the search computes them), then the fine search around
    its pick; (exponent, diffuse fraction, energy)."""
    energy = float(g @ quadrature.weights)
    keep = g > 0
    g32, w32 = g[keep].astype(np.float32), quadrature.weights[keep].astype(np.float32)
    diffuse = (np.maximum(quadrature.directions[keep, 2], 0.0) / np.pi).astype(np.float32)

    def divergences(exponents, fractions):
        glossy = fit.phong_lobe(quadrature.cos_to_axis[keep][None, :], exponents[:, None]).astype(np.float32)
        out = np.empty((len(exponents), len(fractions)))
        for j, t in enumerate(fractions):
            proxy = np.float32(energy * (1 - t)) * glossy + np.float32(energy * t) * diffuse
            out[:, j] = (g32 * g32 / (0.5 * (proxy + g32)) * w32).astype(np.float64).sum(axis=-1) / energy - 1.0
        return out

    coarse = divergences(fit.PHONG_EXPONENTS, fit.DIFFUSE_FRACTIONS)
    i, j = np.unravel_index(np.argmin(coarse), coarse.shape)
    fine_s = fit.FINE_EXPONENTS[i]
    fine_t = np.unique(np.clip(fit.DIFFUSE_FRACTIONS[j] + np.linspace(-0.1, 0.1, 9), 0.0, 1.0))
    fine = divergences(fine_s, fine_t)
    k, l = np.unravel_index(np.argmin(fine), fine.shape)
    return fine_s[k], fine_t[l], energy


@pytest.mark.parametrize("bsdf", [{"type": "roughconductor", "alpha": 0.02}, {"type": "roughconductor", "alpha": 0.3},
                                  {"type": "roughplastic", "alpha": 0.1}, {"type": "diffuse"}])
def test_the_fit_kernels_screened_search_finds_the_whole_grids_fit(bsdf):
    """fit_two_lobes (one kernel a stage, every view node at once) screens its coarse grid on a
    quarter of the nodes and weighs the best few on all of them: at every view node it returns
    the fit of the whole grid weighed on all nodes, then the same fine search. (Where the lobe
    has no glossy part every exponent fits alike, and only the weights are compared.)"""
    from mitsuba_shsampling.lobes import fit

    cosines = np.linspace(0.02, 1.0, 6)
    quadratures = [fit.mirror_quadrature(c) for c in cosines]
    bsdf = mi.load_dict(bsdf)
    lobes = fit.tabulate_lobe(bsdf, cosines, np.stack([q.directions for q in quadratures]),
                              fit.uv_positions(1)).mean(axis=2)
    fits = fit.fit_two_lobes(fit.mean_mirror_lobe(bsdf, cosines, fit.uv_positions(1)), tuple(cosines), np.arange(6))
    for g, quadrature, found in zip(lobes, quadratures, fits):
        exponent, fraction, energy = whole_grid_fit(g, quadrature, fit)
        assert found.diffuse_weight == pytest.approx(energy * fraction, rel=1e-9, abs=1e-12)
        assert found.glossy_weight == pytest.approx(energy * (1 - fraction), rel=1e-9, abs=1e-12)
        if fraction < 1.0:
            assert found.exponent == exponent
