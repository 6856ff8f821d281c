"""The typed report (report/schema.py): what compare writes is what the one loader reads back,
and reports of older formats read as the current one."""

import json
import math

import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.report import verdict  # noqa: E402
from mitsuba_shsampling.report.schema import (UNNAMED_TAIL, PassResult, Report, load_report,  # noqa: E402
                                              serialise)
from mitsuba_shsampling.sweep import aggregate  # noqa: E402


@pytest.fixture(scope="module")
def tiny_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    assert cli.main(["compare", scenes.builtin_scenes()["sphere_ggx010"], "--out", str(out), "--res", "12",
                     "--spp", "2", "--passes", "3", "--ref-spp", "8", "--methods", "direct,env_only,sh_direct",
                     "--convergence-max-spp", "2", "--cache-dir", str(out / "cache"), "--no-progress"]) == 0
    return out / "report.json"


def test_a_real_report_reads_back_typed_and_writes_the_same_json(tiny_report):
    data = json.loads(tiny_report.read_text())
    report = load_report(tiny_report)
    assert isinstance(report, Report) and load_report(report) is report
    run = report.scenes[0].runs[0]
    assert isinstance(run.methods["sh_direct"].equal_time, PassResult)
    assert run.methods["direct"].convergence[0].spp == 1
    assert set(run.maps.files) == {"direct", "env_only", "sh_direct"} and set(run.maps.scale) == {"variance", "rel_error"}
    assert serialise(report) == data


def test_the_verdict_recomputed_from_a_saved_report_is_the_saved_one(tiny_report):
    data = json.loads(tiny_report.read_text())
    assert serialise(verdict.verdict(load_report(tiny_report))) == data["verdict"]


def test_null_is_nan_in_a_float_field_and_none_in_an_optional_one():
    entry = {"spp": 4, "time_s": None, "times_s": [0.1, None], "efficiency": None, "mse_ratio_vs_baseline": None,
             "error": {"mse": None, "mse_per_pass": [None, 0.5], "non_finite": 3}}
    report = load_report({"scenes": [{"runs": [{"methods": {"direct": {"equal_spp": entry}}}]}]})
    passes = report.scenes[0].runs[0].methods["direct"].equal_spp
    assert math.isnan(passes.time_s) and math.isnan(passes.efficiency) and math.isnan(passes.error.mse)
    assert math.isnan(passes.times_s[1]) and passes.error.mse_per_pass[1] == 0.5
    assert passes.mse_ratio_vs_baseline is None


def test_missing_keys_read_as_unknown():
    report = load_report({"scenes": [{"runs": [{"methods": {"direct": {}}}]}]})
    method = report.scenes[0].runs[0].methods["direct"]
    assert report.verdict is None and report.settings is None and math.isnan(report.total_time_s)
    assert method.equal_spp is None and method.family is None and method.compile_time_s is None


def test_an_older_pass_entry_reads_as_the_current_one():
    old = {"spp": 8, "mse": 2.0, "mse_per_pass": [1.0, 3.0], "time_s": 1.0, "bias_ok": False,
           "tail_worse_than_baseline": True}
    passes = load_report({"scenes": [{"runs": [{"methods": {"direct": {"equal_spp": old}}}]}]}) \
        .scenes[0].runs[0].methods["direct"].equal_spp
    assert passes.error.mse == 2.0 and passes.error.mse_per_pass == [1.0, 3.0]  # once at the pass's level
    assert passes.bias.flagged is True and math.isnan(passes.bias.p_value)
    assert passes.tail_worse_than_baseline == [UNNAMED_TAIL]
    ok = load_report({"scenes": [{"runs": [{"methods": {"direct": {"equal_spp": {
        "bias_ok": True, "tail_worse_than_baseline": False}}}}]}]}).scenes[0].runs[0].methods["direct"].equal_spp
    assert ok.bias.flagged is False and ok.tail_worse_than_baseline == []


def test_an_older_material_row_and_verdict_row_read_as_the_current_ones():
    material = {"name": "ground", "plugin": "SmoothDiffuse", "pixel_share": 0.5,
                "variance_ratio": {"sh_direct": {"equal_spp": 0.8, "equal_time": None}},
                "best_mitsuba": {"equal_spp": "direct", "equal_time": "direct"}, "error_share": {"sh_direct": 0.1}}
    cell = {"quantity": "MSE", "winner": "sh_direct", "numerator": "sh_direct", "denominator": "direct",
            "ratio": 0.5, "low": 0.4, "high": 0.6}
    report = load_report({"scenes": [{"runs": [{"materials": {"direct": [material]}}]}],
                          "verdict": [{"scene": "s", "sampler": "independent", "equal_spp": cell}]})
    (row,) = report.scenes[0].runs[0].materials["direct"]
    assert row.error_ratio == {"sh_direct": {"equal_spp": 0.8, "equal_time": None}}
    (verdict_row,) = report.verdict
    assert verdict_row.family == "direct" and verdict_row.equal_spp.numerator_better


def test_the_sweep_summarises_an_older_report_as_the_current_one():
    def current(mse, flagged=False, worse=()):
        e = {"error": {"mse": mse, "mse_per_pass": [mse, mse]}, "time_s": 1.0, "efficiency": 1 / mse,
             "bias": {"flagged": flagged}, "tail_worse_than_baseline": list(worse)}
        return {"equal_spp": e, "equal_time": e}

    def older(mse, flagged=False, worse=()):
        e = {"mse": mse, "mse_per_pass": [mse, mse], "time_s": 1.0, "efficiency": 1 / mse,
             "bias_ok": not flagged, "tail_worse_than_baseline": bool(worse)}
        return {"equal_spp": e, "equal_time": e}

    summaries = [aggregate.summarise_report({"scenes": [{"notes": [], "runs": [{"methods": {
        "direct": kind(1.0), "sh_direct": kind(0.5, flagged=True, worse=["a tail"])}}]}]}) for kind in (current, older)]
    assert summaries[0] == summaries[1]
    assert summaries[0]["bias"] == "flagged: sh_direct" and summaries[0]["methods"]["sh_direct"]["tail_ok"] is False
