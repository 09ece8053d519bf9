"""``sb3-formation benchmark``: the table, the evaluations and the figures of a small run; its refusals."""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

import pytest

from sb3_formation import __version__
from sb3_formation.cli import main
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.evaluation import load_summary


def test_benchmark_writes_the_table_evaluations_and_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two episodes per scene set (four in the crossing of four formations): a row per scene set in the printed table
    and in benchmark.md, figures of each, and every figure of benchmark.json is the stored evaluation's (success,
    shape error = bearing error over the successes, contacts over all episodes)."""
    out = tmp_path / "bench"
    arguments = ["benchmark", "controller:classical", "--episodes", "2", "--workers", "1", "--out", str(out)]
    assert main([*arguments, "--no-progress", "--labels", "classical"]) == 0
    printed = capsys.readouterr().out
    table = (out / "benchmark.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| classical |")]
    assert [row.split(" | ")[1] for row in rows] == list(BENCHMARK_SCENES)
    assert table.strip() in printed
    results = json.loads((out / "benchmark.json").read_text())
    run = results["run"]
    assert run["command"] == shlex.join(["sb3-formation", *arguments, "--no-progress", "--labels", "classical"])
    assert table.startswith(f"sb3-formation {__version__} benchmark, {run['machine']}: `{run['command']}`")
    assert "2 episodes per scene set from seed 10000" in table.splitlines()[1]
    assert [row["scenes"] for row in results["rows"]] == list(BENCHMARK_SCENES)
    headings = table.splitlines()[3].strip("| ").split(" | ")
    for row, line in zip(results["rows"], rows):
        cells = dict(zip(headings, line.strip("| ").split(" | ")))
        assert row["seconds"] > 0 and cells["seconds"] == f"{row['seconds']:.0f}"
        assert cells["filter changed"] == cells["min separation (m)"] == "-"  # not filtered
        summary = load_summary(out / "classical" / row["scenes"])
        n = 4 if row["scenes"] == "crossing-4" else 2  # a crossing of four formations: an episode each
        assert summary["scenes"] == row["scenes"] and summary["seed"] == 10_000 and summary["episodes"] == n
        assert row["success_rate"] == summary["success_rate"]
        # Wilson's 95 % interval of n episodes, by its formula
        z, p = 1.959964, row["success_rate"]
        centre, half = (
            (p + z * z / (2 * n)) / (1 + z * z / n),
            z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)),
        )
        assert row["success_rate_ci95"] == pytest.approx([centre - half, centre + half], abs=1e-5)
        assert row["shape_error"] == summary["successful_episodes"]["bearing_error"]["mean"]
        assert row["obstacle_contacts"] == summary["all_episodes"]["collisions_obstacle"]["mean"]
        assert (out / "figures" / f"classical_{row['scenes']}.png").stat().st_size > 10_000
    # a reused folder is refused before anything is written
    before = sorted(path.stat().st_mtime_ns for path in out.rglob("*"))
    assert main([*arguments, "--no-progress"]) == 2
    assert "already holds files" in capsys.readouterr().err
    assert sorted(path.stat().st_mtime_ns for path in out.rglob("*")) == before


def test_benchmark_reports_what_the_filter_did_for_a_safe_target(tmp_path: Path) -> None:
    """A ``safe:`` target's rows give the filter's share of changed agent-steps, its mean change, infeasible steps and
    the smallest separation, each the stored evaluation's; its contact episodes count the episodes with contacts. On
    the static scene sets (``--scenes`` picks them) the filter keeps every agent clear of every shape."""
    out = tmp_path / "bench"
    static = "curriculum,passage,corridor,trap,clutter"
    arguments = ["benchmark", "safe:controller:random", "--episodes", "2", "--workers", "1", "--scenes", static]
    arguments += ["--out", str(out)]
    assert main([*arguments, "--no-progress", "--labels", "random", "--agents", "3"]) == 0
    results = json.loads((out / "benchmark.json").read_text())
    assert [row["scenes"] for row in results["rows"]] == static.split(",")
    for row in results["rows"]:
        summary = load_summary(out / "random" / row["scenes"])
        episodes = summary["all_episodes"]
        assert summary["model"]["safety"]["gamma"] == 0.5 and summary["model"]["policy"]["controller"] == "RandomController"
        assert row["filter_changed"] == episodes["filter_changed_fraction"]["mean"]
        assert row["filter_change"] == episodes["filter_change_mean"]["mean"]
        assert row["infeasible_steps"] == episodes["filter_infeasible_steps"]["mean"]
        assert row["min_separation"] == summary["min_separation"] > 0
        assert row["contact_episodes"] == sum(summary["episodes_with_contacts"].values())
