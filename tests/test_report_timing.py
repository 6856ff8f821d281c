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
    jobs = {name: (FakeRenderer(name, log), 4) for name in ("direct", "sh_direct", "direct_misc")}
    passes, failed = interleaved_passes(jobs, count=3, seed0=10)
    assert not failed
    assert log == [(name, 10 + k) for k in range(3) for name in ("direct", "sh_direct", "direct_misc")]
    for name, result in passes.items():
        assert result.seeds == [10, 11, 12] and result.images.shape == (3, 2, 2, 3)
        assert result.images[:, 0, 0, 0].tolist() == [10.0, 11.0, 12.0]


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


def row(budget_s, spp=8):
    entry = {"spp": spp, "time_s": budget_s, "time_budget_s": budget_s, "times_s": [budget_s],
             "tail_worse_than_baseline": [], "bias": {"flagged": False, "p_value": 0.5},
             "error": {"non_finite": 0}}
    return {"equal_spp": dict(entry), "equal_time": dict(entry)}


def test_caveats_need_no_row_of_a_baseline_that_failed_at_equal_time():
    """A baseline dropped in the equal-time phase leaves the others' budgets with them."""
    from mitsuba_shsampling.report.verdict import _caveats
    run = {"methods": {"sh_direct": row(0.005), "direct_misc": row(0.005)}}
    notes = _caveats({}, run, ["sh_direct", "direct_misc"], "direct", ["sh_direct", "direct_misc"],
                     ["sh_direct", "direct_misc"])
    assert any("time budget too small" in n for n in notes)
