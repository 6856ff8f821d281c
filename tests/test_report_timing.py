"""Specification of how a comparison times its methods: interleaved, so that the
machine's slow spells fall on every method alike (report/rendering.py)."""

from __future__ import annotations

import types

import numpy as np

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.report.rendering import interleaved_passes  # noqa: E402


class FakeRenderer:
    """Stands in for MethodRenderer: records the order of its renders."""

    def __init__(self, name, log, fail_at=None):
        self.method = types.SimpleNamespace(name=name)
        self.sampler_name = "independent"
        self.warm_spps, self.first_render_s, self.compile_time_s = set(), None, None
        self.log, self.fail_at, self.renders = log, fail_at, 0

    def warm_up(self, spp):
        self.warm_spps.add(spp)
        self.first_render_s = 1.0

    def render(self, spp, seed):
        if self.fail_at is not None and self.renders == self.fail_at:
            raise RuntimeError(f"{self.method.name} broke")
        self.renders += 1
        self.log.append((self.method.name, seed))
        return np.full((2, 2, 3), float(seed), dtype=np.float32), 0.01

    def actual_spp(self):
        return 4


def test_pass_k_of_every_method_runs_before_pass_k_plus_1_of_any():
    log = []
    names = ("direct", "sh_direct", "direct_misc")
    jobs = {name: (FakeRenderer(name, log), 4) for name in names}
    passes, failed = interleaved_passes(jobs, count=3, seed0=10)
    assert not failed
    assert [seed for _, seed in log] == [10] * 3 + [11] * 3 + [12] * 3
    for k in range(3):
        assert sorted(name for name, _ in log[3 * k:3 * k + 3]) == sorted(names)
    for name, result in passes.items():
        assert result.seeds == [10, 11, 12] and result.images.shape == (3, 2, 2, 3)
        assert result.images[:, 0, 0, 0].tolist() == [10.0, 11.0, 12.0]


def test_the_order_of_the_methods_rotates_from_pass_to_pass():
    """No method always renders first (or always after the same one): position effects of the
    round robin fall on every method alike."""
    log = []
    jobs = {name: (FakeRenderer(name, log), 4) for name in ("direct", "sh_direct", "direct_misc")}
    interleaved_passes(jobs, count=4, seed0=0)
    orders = [[name for name, seed in log if seed == k] for k in range(4)]
    assert orders == [["direct", "sh_direct", "direct_misc"], ["sh_direct", "direct_misc", "direct"],
                      ["direct_misc", "direct", "sh_direct"], ["direct", "sh_direct", "direct_misc"]]


def test_the_rotation_skips_a_method_that_failed():
    log = []
    jobs = {"direct": (FakeRenderer("direct", log), 4), "broken": (FakeRenderer("broken", log, fail_at=1), 4),
            "sh_direct": (FakeRenderer("sh_direct", log), 4)}
    interleaved_passes(jobs, count=3, seed0=0)
    orders = [[name for name, seed in log if seed == k] for k in range(3)]
    assert orders == [["direct", "broken", "sh_direct"], ["sh_direct", "direct"], ["sh_direct", "direct"]]


def test_a_method_that_fails_is_reported_and_the_others_still_get_every_pass():
    log = []
    jobs = {"direct": (FakeRenderer("direct", log), 4), "broken": (FakeRenderer("broken", log, fail_at=1), 4)}
    passes, failed = interleaved_passes(jobs, count=3, seed0=0)
    assert set(passes) == {"direct"} and str(failed["broken"]) == "broken broke"
    assert len(passes["direct"].times_s) == 3
    assert [seed for name, seed in log if name == "broken"] == [0]


def test_the_first_untimed_render_gives_the_compile_time():
    renderer = FakeRenderer("direct", [])
    interleaved_passes({"direct": (renderer, 4)}, count=2, seed0=0)
    assert renderer.compile_time_s == 1.0 - 0.01


def timed_run(budgets_s: dict[str, float], spp=8):
    """A run as the verdict reads it: per method, both comparisons taking their budget."""
    from mitsuba_shsampling.report.schema import load_report

    def entry(budget_s):
        return {"spp": spp, "time_s": budget_s, "time_budget_s": budget_s, "times_s": [budget_s],
                "tail_worse_than_baseline": [], "bias": {"flagged": False, "p_value": 0.5},
                "error": {"non_finite": 0}}
    methods = {n: {"equal_spp": entry(b), "equal_time": entry(b)} for n, b in budgets_s.items()}
    return load_report({"scenes": [{"runs": [{"methods": methods}]}]}).scenes[0].runs[0]


def test_caveats_need_no_row_of_a_baseline_that_failed_at_equal_time():
    """A baseline dropped in the equal-time phase leaves the others' budgets with them."""
    from mitsuba_shsampling.report.verdict import _caveats
    run = timed_run({"sh_direct": 0.005, "direct_misc": 0.005})
    notes = _caveats("s.xml", run, ["sh_direct", "direct_misc"], "direct", ["sh_direct", "direct_misc"],
                     ["sh_direct", "direct_misc"])
    assert any("time budget too small" in n for n in notes)


def test_a_baseline_whose_pass_time_changed_between_the_phases_makes_the_budget_unreliable():
    from mitsuba_shsampling.report.verdict import _caveats
    run = timed_run({"direct": 0.080, "sh_direct": 0.080})
    names = ["direct", "sh_direct"]
    assert not any("unreliable" in n for n in _caveats("s.xml", run, names, "direct", names, names))
    run.methods["direct"].equal_spp.time_s = 0.416  # a busy or cold machine in the first phase
    notes = _caveats("s.xml", run, names, "direct", names, names)
    assert any(n.startswith("time budget unreliable: a direct pass took 5.2x") for n in notes)


def test_no_render_is_timed_before_its_method_rendered_that_spp_once_untimed(tmp_path, monkeypatch):
    """Compile (a new spp recompiles with most samplers) and scene set-up stay out of every pass
    time, the equal-time budget and the convergence sweep."""
    from mitsuba_shsampling import cli, scenes
    from mitsuba_shsampling.report import rendering

    log = []
    untimed_render = rendering.MethodRenderer.render

    def logged_render(self, spp, seed):
        log.append((id(self), spp, seed))
        return untimed_render(self, spp, seed)

    monkeypatch.setattr(rendering.MethodRenderer, "render", logged_render)
    assert cli.main(["compare", scenes.builtin_scenes()["sphere_diffuse"], "--out", str(tmp_path), "--res", "8",
                     "--spp", "2", "--passes", "2", "--ref-spp", "8", "--sampler", "multijitter",
                     "--methods", "direct,sh_direct", "--convergence-max-spp", "8",
                     "--cache-dir", str(tmp_path / "cache"), "--no-progress"]) == 0
    first_seed = {}
    for renderer, spp, seed in log:
        first_seed.setdefault((renderer, spp), seed)
    assert len(first_seed) >= 2 * 3  # two methods, several spp (convergence 1, 2, 4, 8)
    assert set(first_seed.values()) == {rendering.SEED_WARMUP}
