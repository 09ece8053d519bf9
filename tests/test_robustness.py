"""Robustness curves (``sb3-formation robustness``, :mod:`sb3_formation.experiment.robustness`): level 0 is the ideal
world's evaluation, other levels and each factor alone change the episodes, the table, the data and the curves; the
refusals before any work."""

from __future__ import annotations

import csv
import json
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

from sb3_formation import __version__, load_policy
from sb3_formation.cli import build_parser, main
from sb3_formation.env.disturbances import PARTS, load_disturbances
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.benchmark import BENCHMARK_EPISODES, BENCHMARK_SEED
from sb3_formation.experiment.evaluation import EvaluationResult, evaluate, load_summary
from sb3_formation.experiment.robustness import (
    ALL_PARTS,
    ROBUSTNESS_LEVELS,
    RobustnessRow,
    check_profile,
    read_robustness,
    robustness_factors,
    run_robustness,
)
from sb3_formation.utils.files import folder_lock

EPISODES = 3
SIGNALS = ("sensing", "acting", "timing", "communication")  # the parts realistic disturbs (it has no failures)
FACTORS = (ALL_PARTS, *SIGNALS)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[RobustnessRow]]:
    """``controller:classical`` under ``realistic`` at levels 0 and 1, every factor, 3 episodes of stage 3."""
    out = tmp_path_factory.mktemp("sweep") / "robustness"
    rows = run_robustness(
        ["controller:classical"], ["classical"], out, levels=[1, 0], episodes=EPISODES, scenes=["curriculum"], workers=1
    )
    return out, rows


def point(rows: list[RobustnessRow], factor: str, level: float) -> EvaluationResult:
    """The evaluation of the sweep's point (factor, level)."""
    (row,) = [row for row in rows if row.factor == factor and row.level == level]
    return row.result


def test_level_0_is_the_ideal_evaluation_for_every_factor(sweep: tuple[Path, list[RobustnessRow]]) -> None:
    """Level 0 gives, episode for episode, what ``evaluate`` gives without disturbances (the benchmark's protocol), and
    its files are written under every factor."""
    out, rows = sweep
    policy = load_policy("controller:classical")
    ideal = evaluate(policy, EPISODES, 3, BENCHMARK_SEED, n_envs=EPISODES, env_overrides={"scenes": "curriculum"}, record=1)
    for factor in FACTORS:
        result = point(rows, factor, 0.0)
        assert result.episodes == ideal.episodes and result.summary == ideal.summary
        assert "disturbances" not in result.summary
        folder = out / "classical" / factor / "0" / "curriculum"
        assert (folder / "episodes.csv").read_text() == ideal.episode_table()
        assert load_summary(folder)["seed"] == BENCHMARK_SEED


def test_a_level_changes_the_episodes_and_each_factor_alone_differs_from_the_whole(
    sweep: tuple[Path, list[RobustnessRow]],
) -> None:
    """At level 1 the whole profile changes the episodes; each part alone gives other episodes than the whole, and its
    summary records that part only. The communication part alone leaves a controller's episodes as the ideal world's:
    a controller sends no messages."""
    out, rows = sweep
    ideal, whole = point(rows, ALL_PARTS, 0.0), point(rows, ALL_PARTS, 1.0)
    assert whole.episodes != ideal.episodes
    assert whole.summary["disturbances"] == load_disturbances("realistic").to_dict()
    for part in SIGNALS:
        alone = point(rows, part, 1.0)
        assert alone.episodes != whole.episodes, part
        assert alone.summary["disturbances"] == load_disturbances("realistic").only(part).to_dict()
        assert load_summary(out / "classical" / part / "1" / "curriculum")["disturbances"] == alone.summary["disturbances"]
    for part in ("sensing", "acting", "timing"):
        assert point(rows, part, 1.0).episodes != ideal.episodes, part
    assert point(rows, "communication", 1.0).episodes == ideal.episodes


def table_rows(out: Path) -> list[dict[str, str]]:
    """The rows of ``robustness.md``, by heading."""
    lines = [line for line in (out / "robustness.md").read_text().splitlines() if line.startswith("|")]
    headings = lines[0].strip("| ").split(" | ")
    return [dict(zip(headings, line.strip("| ").split(" | "))) for line in lines[2:]]


def test_the_table_has_a_row_per_point_and_the_data_round_trips(sweep: tuple[Path, list[RobustnessRow]]) -> None:
    """One row per (target, factor, level, scene set), level ascending; ``robustness.json`` reads back as the rows'
    cells, with the run's provenance and profile; every cell is the stored evaluation's."""
    out, rows = sweep
    table = table_rows(out)
    points = [(row["target"], row["factor"], row["level"], row["scenes"]) for row in table]
    assert points == [("classical", factor, level, "curriculum") for factor in FACTORS for level in ("0", "1")]
    data = read_robustness(out)
    assert data["rows"] == [row.cells() for row in rows]
    assert json.loads(json.dumps(data)) == data
    run = data["run"]
    assert run["version"] == __version__ and run["command"] == "" and run["levels"] == [0.0, 1.0]
    assert run["factors"] == list(FACTORS) and run["profile"]["name"] == "realistic"
    assert run["profile"]["disturbances"] == load_disturbances("realistic").to_dict()
    assert f"{EPISODES} episodes per point and scene set from seed {BENCHMARK_SEED}, stage 3" in run["protocol"]
    header = (out / "robustness.md").read_text().splitlines()
    assert header[0] == f"sb3-formation {__version__} robustness curves, {run['machine']}: run from Python.  "
    for cells, line in zip(data["rows"], table):
        summary = load_summary(out / cells["folder"])
        with open(out / cells["folder"] / "episodes.csv") as stream:
            episodes = list(csv.DictReader(stream))
        touched = sum(float(row["collisions_agent"]) > 0 or float(row["collisions_obstacle"]) > 0 for row in episodes)
        assert cells["success_rate"] == summary["success_rate"] and cells["episodes_with_contacts"] == touched
        assert cells["shape_error"] == summary["successful_episodes"]["bearing_error"]["mean"]
        low, high = summary["success_rate_ci95"]
        assert line["success (95 % CI)"] == f"{summary['success_rate']:.0%} ({low:.0%} - {high:.0%})"
        assert line["episodes with contacts (95 % CI)"].startswith(f"{touched / len(episodes):.0%} (")


def test_the_curves_are_drawn_from_the_data(sweep: tuple[Path, list[RobustnessRow]], tmp_path: Path) -> None:
    """A figure per scene set from the rows read back: a row of panels per factor, three panels each."""
    from sb3_formation.viz.plots import plot_robustness, save_figures

    out, _ = sweep
    figure = plot_robustness(read_robustness(out)["rows"])
    assert len(figure.axes) == 3 * len(FACTORS)
    (path,) = save_figures({tmp_path / "robustness_curriculum.png": figure})
    assert path.stat().st_size > 20_000
    with pytest.raises(ValueError, match="no rows of the scene set 'trap'"):
        plot_robustness(read_robustness(out)["rows"], "trap")


def randomised_file(folder: Path) -> Path:
    path = folder / "randomised.yaml"
    path.write_text(yaml.safe_dump({"profile": "realistic", "randomise": True}))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"levels": 0.5}, "levels must be a list of numbers"),
        ({"levels": [0, -1]}, "a level must be a finite number in [0, 10], got -1"),
        ({"levels": [0, float("nan")]}, "a level must be a finite number in [0, 10], got nan"),
        ({"levels": [0, 11]}, "a level must be a finite number in [0, 10], got 11"),
        ({"levels": [0, True]}, "a level must be a finite number in [0, 10], got True"),
        ({"levels": [1, 1.0]}, "levels must differ"),
        ({"levels": []}, "give 1 to 20 levels, got 0"),
        ({"factors": ["sensing", "wind"]}, "unknown factor 'wind'"),
        ({"factors": "sensing"}, "factors must be true, false or a list of parts"),
        ({"labels": ["a", "a"], "targets": ["controller:classical", "controller:random"]}, "one distinct label per target"),
        ({"labels": ["../a"]}, "label '../a' is not a single file name"),
        ({"labels": ["robustness.md"]}, "label 'robustness.md' is the name of a file the sweep writes"),
        ({"disturbances": "ideal"}, "disturbances ideal have no error to scale"),
        ({"disturbances": "stormy"}, "neither a profile"),
        ({"disturbances": "randomised"}, "draw their level per episode (randomise: true)"),
        ({"scenes": ["mixed"]}, "unknown scene set(s) ['mixed']"),
    ],
)
def test_invalid_inputs_are_refused_before_any_work(changes: dict[str, Any], message: str, tmp_path: Path) -> None:
    """One line naming the problem, nothing written."""
    out = tmp_path / "out"
    if changes.get("disturbances") == "randomised":
        changes["disturbances"] = randomised_file(tmp_path)
    arguments: dict[str, Any] = {"targets": ["controller:classical"], "labels": ["classical"], "out": out} | changes
    with pytest.raises(ValueError) as error:
        run_robustness(arguments.pop("targets"), arguments.pop("labels"), arguments.pop("out"), **arguments)
    assert message in str(error.value) and "\n" not in str(error.value)
    assert not out.exists()


def test_a_folder_that_holds_files_is_refused(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="already holds files"):
        run_robustness(["controller:classical"], ["classical"], tmp_path, levels=[0])
    assert [path.name for path in tmp_path.iterdir()] == ["notes.txt"]


def test_the_factors_are_the_parts_a_profile_disturbs(tmp_path: Path) -> None:
    """Every part of ``realistic``; none beside ``all`` for a profile of one part (it is ``all``); a chosen list."""
    realistic = load_disturbances("realistic")
    assert SIGNALS == tuple(part for part in PARTS if part != "failures")
    assert robustness_factors(realistic) == FACTORS and robustness_factors(realistic, False) == (ALL_PARTS,)
    assert robustness_factors(realistic, ["timing"]) == (ALL_PARTS, "timing")
    lidar = tmp_path / "lidar.yaml"
    lidar.write_text(yaml.safe_dump({"sensing": {"lidar_noise": 0.02}}))
    assert robustness_factors(check_profile(lidar)) == (ALL_PARTS,)
    with pytest.raises(ValueError, match="no timing errors to scale"):
        robustness_factors(check_profile(lidar), ["timing"])


# The command line ------------------------------------------------------------------------------------------------------


def test_the_command_s_defaults_are_the_functions() -> None:
    args = build_parser().parse_args(["robustness", "controller:classical"])
    assert args.levels == ROBUSTNESS_LEVELS and args.disturbances == "realistic" and not args.no_factors
    assert args.episodes == BENCHMARK_EPISODES and args.seed == BENCHMARK_SEED and args.scenes == BENCHMARK_SCENES
    assert args.out == Path("robustness") and args.n_envs == 16 and args.workers == 2 and args.recipe is None
    assert args.device == "auto" and not args.no_progress and not args.trust_pickle and args.labels is None


def test_the_command_writes_the_table_evaluations_and_curves(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every option once: the printed table is the file's, a row per level, the evaluations and a figure per scene set;
    the same --out again is refused before anything is written, as is a folder another sweep holds."""
    out = tmp_path / "rob"
    arguments = ["robustness", "controller:classical", "--disturbances", "harsh", "--levels", "0,1", "--no-factors"]
    arguments += ["--episodes", "2", "--seed", str(BENCHMARK_SEED), "--scenes", "curriculum", "--n-envs", "2"]
    arguments += ["--workers", "1", "--labels", "classical", "--out", str(out), "--recipe", "ch5-bearing"]
    arguments += ["--device", "cpu", "--no-progress", "--trust-pickle"]
    assert main(arguments) == 0
    printed = capsys.readouterr().out
    table = (out / "robustness.md").read_text()
    assert printed.startswith(f"robustness of controller:classical under harsh into {out}")
    assert table.strip() in printed and f"curves to {out / 'figures'}" in printed
    assert [(row["factor"], row["level"]) for row in table_rows(out)] == [("all", "0"), ("all", "1")]
    run = read_robustness(out)["run"]
    assert run["command"] == shlex.join(["sb3-formation", *arguments]) and run["profile"]["name"] == "harsh"
    assert load_summary(out / "classical" / "all" / "1" / "curriculum")["disturbances"] == load_disturbances("harsh").to_dict()
    assert (out / "figures" / "robustness_curriculum.png").stat().st_size > 10_000
    assert not (out / ".lock").exists()
    before = sorted((str(path), path.stat().st_mtime_ns) for path in out.rglob("*"))
    assert main(arguments) == 2
    assert "already holds files: give a new or empty --out" in capsys.readouterr().err
    assert sorted((str(path), path.stat().st_mtime_ns) for path in out.rglob("*")) == before
    busy = tmp_path / "busy"
    with folder_lock(busy, "robustness folder"):  # as a sweep running in another process holds it
        assert main([*arguments[:-6], "--out", str(busy), "--no-progress"]) == 2
    assert "is in use by another process" in capsys.readouterr().err
    assert [path.name for path in busy.iterdir()] == [".lock"]


@pytest.mark.parametrize(
    ("levels", "message"),
    [
        ("0,-1", "a level must be a finite number in [0, 10], got -1.0"),
        ("0,nan", "got nan"),
        ("0,inf", "got inf"),
        ("0,12", "got 12.0"),
        ("0,1,1", "levels must differ"),
        ("0,a", "expected levels such as 0,0.5,1, got '0,a'"),
        ("", "expected levels such as 0,0.5,1"),
    ],
)
def test_bad_levels_are_one_line_and_exit_code_2_before_any_file(
    levels: str, message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["robustness", "controller:classical", "--levels", levels, "--episodes", "2"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith("sb3-formation: error: argument --levels: ") and error.count("\n") == 1, error
    assert message in error
    assert list(tmp_path.iterdir()) == []


def test_an_ideal_profile_is_refused_before_any_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["robustness", "controller:classical", "--disturbances", "ideal", "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("sb3-formation: error: disturbances ideal have no error to scale: give a profile such as")
    assert error.count("\n") == 1
    assert list(tmp_path.iterdir()) == []
