"""Specification: ``scripts/bench_material_pilots.py`` fits the prior of
``integrators/material_pilots.py`` to measured material differences by maximum likelihood."""

import importlib.util
import os

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_material_pilots",
                                                  os.path.join(REPO, "scripts", "bench_material_pilots.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_fit_recovers_the_prior_that_made_the_measurements(bench):
    """Measurements made from a known two-part prior (the quadrature off by 8 % of the
    environment variance, or in one material of twenty by up to all of it) give that prior
    back, and a single normal prior fits them worse."""
    rng = np.random.default_rng(5)
    rows = []
    for _ in range(600):
        env = rng.uniform(0.5, 2.0)
        predicted = rng.uniform(0.0, 0.5) * env
        missed = rng.random() < 0.05
        truth = predicted + rng.normal(0.0, env if missed else 0.08 * env)
        error = rng.uniform(0.005, 0.05) * env
        rows.append({"predicted": predicted, "measured": truth + rng.normal(0.0, error), "error": error,
                     "environment": env, "environment_pilot": env})
    result = bench.fit(rows)
    assert result["measurements"] == 600
    assert result["close"] == pytest.approx(0.08, abs=0.015)
    assert result["missed_share"] == pytest.approx(0.05, abs=0.03)
    assert result["single_normal"]["log_likelihood"] < result["log_likelihood"]
    assert 0 < result["precise_off"]["median"] < 0.08


def test_every_readme_cell_is_planned(bench):
    cells = bench.cells()
    assert len(cells) == 2 * 5 * 2 + 9 * 5
    assert {c[3]["type"] for c in cells} == {"sh_direct", "sh_path"}


def test_the_plans_that_changed_are_listed_material_by_material(bench):
    before = {"studio|sunsky|sh_direct": {"gold": "environment", "ground": "environment"},
              "studio|sunsky|sh_path": {"gold": "lean", "ground": "lean"},
              "sphere|forest|sh_direct": {"ball": "product"}}
    after = {"studio|sunsky|sh_direct": {"gold": "product", "ground": "environment"},
             "studio|sunsky|sh_path": {"gold": "product", "ground": "environment"},
             "sphere|forest|sh_direct": {"ball": "product"}}
    assert bench.changed_plans(before, after) == {
        "studio|sunsky|sh_direct": {"gold": ("environment", "product")},
        "studio|sunsky|sh_path": {"gold": ("lean", "product"), "ground": ("lean", "environment")}}
    assert bench.plan_summary({"lean": True, "materials": [{"name": "gold", "strategy": "environment"}]}) == \
        {"gold": "lean"}
