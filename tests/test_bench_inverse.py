"""Specification: ``scripts/bench_inverse.py`` runs inverse problems with ``sh_prb``, ``prb`` and
``prb`` + ``mis_compensation`` on their own clocks, scores loss and parameter error against
seconds, and summarises per task the step times and the time each method takes to reach a
reference's final loss."""

import json
import math
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = os.path.join(REPO, "scripts")
sys.path.insert(0, SCRIPTS)

import bench_inverse  # noqa: E402

METHODS = {"sh_prb (plan every 2)", "sh_prb (plan every 8)", "prb", "prb + mis_compensation"}


def test_the_envmap_task_runs_every_method_on_its_own_clock_and_writes_json_and_a_plot(tmp_path):
    """One ``sh_prb`` run per ``--plan-every`` value beside Mitsuba's two."""
    out, png = tmp_path / "inverse.json", tmp_path / "inverse.png"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(SCRIPTS, "bench_inverse.py"), "--tasks", "envmap",
                           "--seeds", "1", "--seconds", "0.5", "--plan-every", "2", "8", "--res", "16", "--eval-spp", "4", "--target-spp", "1024",
                           "--json", str(out), "--plot", str(png)],
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    written = json.loads(out.read_text())
    runs = written["runs"]["envmap"]["0"]
    assert set(runs) == METHODS
    for run in runs.values():
        assert run["seconds"] >= 0.5 and run["steps"] > 0
        history = run["history"]
        assert history[0]["seconds"] == 0.0 and len(history) >= 2
        assert all(math.isfinite(h["loss"]) and math.isfinite(h["parameter_error"]) for h in history)
        # The start is a flat grey: its error is the map's own contrast, far from 0.
        assert history[0]["parameter_error"] > 0.1
    assert set(written["summary"]["envmap"]) == METHODS
    assert written["summary"]["envmap"]["prb"]["step_ratio_to_prb"] == 1.0
    assert png.stat().st_size > 10_000


def history(*losses, every=1.0):
    return {"history": [{"seconds": k * every, "loss": loss, "parameter_error": loss} for k, loss in enumerate(losses)],
            "median_step_s": 0.01, "mean_step_s": 0.01, "state_builds": 0}


def test_a_methods_late_loss_is_its_second_halfs_mean_and_the_time_to_reach_one_is_its_first_score_below():
    seeds = {0: {"sh_prb": history(1.0, 0.5, 0.2, 0.1), "prb": history(1.0, 0.6, 0.4, 0.2),
                 "prb + mis_compensation": history(1.0, 0.9, 0.02, 0.02)}}
    summary = bench_inverse.summarise({"task": seeds}, seconds=3.0)["task"]
    # Second half: the scores at 2 s and 3 s of the 3 s budget.
    assert summary["prb"]["late_loss"] == pytest.approx(0.3)
    assert summary["sh_prb"]["late_loss"] == pytest.approx(0.15)
    assert summary["sh_prb"]["time_to_prb_late_loss"] == [2.0 / 3.0]  # 0.2 <= 0.3, first at 2 s
    assert summary["prb"]["time_to_prb_late_loss"] == [1.0]  # 0.4 > 0.3: only its last score
    # Over the reference's own time to its late loss: 2 s against 3 s.
    assert summary["sh_prb"]["time_ratio_to_prb"] == pytest.approx(2.0 / 3.0)
    assert summary["sh_prb"]["time_to_prb + mis_compensation_late_loss"] == [math.inf]
    assert summary["sh_prb"]["final_loss"] == 0.1


def test_the_parameter_error_weighs_each_value_by_where_the_image_depends_on_it():
    import numpy as np

    task = bench_inverse.Task("t", None, {"x": 0.0}, {"x": (0, 1)}, 0.1)
    task.truth, task.weights = {"x": np.array([1.0, 1.0])}, {"x": np.array([1.0, 0.0])}

    class Params(dict):
        def __getitem__(self, key):
            return type("V", (), {"numpy": lambda _: np.array([1.5, 9.0])})()

    # The second value is wrong by 8 but unseen (weight 0): only the first one's 50 % counts.
    assert task.parameter_error(Params()) == 0.5
