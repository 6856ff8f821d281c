"""A method's role (project, Mitsuba strategy, reference row) has one definition, and the
verdict, the sweep aggregate and the README table take "the best Mitsuba strategy" from it."""

import importlib.util
import os

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.report import verdict  # noqa: E402
from mitsuba_shsampling.report.methods import (DIRECT, METHODS, MITSUBA, PROJECT, REFERENCE,  # noqa: E402
                                               mitsuba_strategies)
from mitsuba_shsampling.sweep import aggregate  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def results_table():
    spec = importlib.util.spec_from_file_location("results_table", os.path.join(REPO, "scripts", "results_table.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def entry(mse: float, family: str = DIRECT) -> dict:
    """A report.json method entry with every field the consumers read; time 1 s per pass."""
    kind = {"spp": 8, "time_s": 1.0, "times_s": [1.0] * 4, "efficiency": 1.0 / mse,
            "error": {"mse": mse, "mse_per_pass": [mse] * 4, "non_finite": 0},
            "bias": {"flagged": False, "p_value": 0.5}, "tail_worse_than_baseline": [],
            "tail": {"max_pixel": 10.0, "abs_error_percentile": 1.0, "fireflies": 0},
            "budget_method": "direct", "time_budget_s": 1.0}
    return {"family": family, "equal_spp": dict(kind), "equal_time": dict(kind), "compile_time_s": 0.0,
            "oracle": False}


def test_every_method_has_one_of_the_three_roles_and_the_plugin_follows_from_it():
    assert {m.role for m in METHODS} == {PROJECT, MITSUBA, REFERENCE}
    for m in METHODS:
        assert (m.plugin is None) == (m.role == MITSUBA)
        assert m.oracle == (m.role == REFERENCE)


def test_best_mitsuba_is_one_set_for_the_verdict_the_aggregate_and_the_readme_table():
    # bsdf_only is the best Mitsuba strategy here: every consumer must say so.
    methods = {"direct": entry(4.0), "env_only": entry(3.0), "bsdf_only": entry(2.0),
               "sh_direct": entry(1.0), "oracle_only": entry(0.5)}
    report = {"settings": {"envmap": None}, "scenes": [{
        "scene": "s", "path": "s.xml", "references": {}, "notes": [],
        "runs": [{"sampler": "independent", "methods": methods}]}]}
    assert mitsuba_strategies(methods) == ["direct", "env_only", "bsdf_only"]

    (row,) = verdict.verdict(report)
    assert (row.equal_spp.numerator, row.equal_spp.denominator) == ("sh_direct", "bsdf_only")
    assert row.equal_spp.winner == "sh_direct"  # the reference row is no contender

    summary = aggregate.summarise_report(report)
    assert summary["best_mitsuba_mse"] == summary["best_mitsuba_efficiency"] == "bsdf_only"
    assert summary["winner"] == "sh_direct"

    (table_row,) = results_table().rows(report, "direct")
    assert table_row["best_mse"] == table_row["best_eff"] == "bsdf_only"
    assert table_row["mse_vs_best"] == 0.5
