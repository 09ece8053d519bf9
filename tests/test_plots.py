"""Figures: trajectories, error curves, evaluation bars, training curves from real TensorBoard events, and saving."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.container import BarContainer
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon
from PIL import Image

from sb3_formation.env.config import FormationConfig
from sb3_formation.experiment.evaluation import EvaluationResult
from sb3_formation.experiment.recipes import layered_settings
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.viz.plots import (
    formation_steps,
    load_training_curves,
    plot_error_curves,
    plot_evaluation_bars,
    plot_training_curves,
    plot_trajectory,
    rolling_mean,
    save_figure,
    steps_per_iteration,
)

LENGTHS = (6, 3)  # two episodes of different lengths; the second is NaN-padded after row 3
OBSTACLE_HIT = (0, 2, 1)  # (episode, step, agent) of the obstacle collision
AGENT_HITS = ((0, 4, 0), (0, 4, 2))  # a touching pair, counted by both agents


def make_trajectories() -> Trajectories:
    """Two hand-made episodes of three agents: agent i at (2 + i + 0.5 t + k, 3 + 0.25 t + 0.3 i (i mod 2)) in episode k;
    angle error 10 t + i (deg), neighbour-distance error 0.1 t (i + 1) (m)."""
    config = FormationConfig.task("ch4-individual")
    n_agents, rows = config.n_agents, max(LENGTHS) + 1
    positions = np.full((2, rows, n_agents, 2), np.nan)
    angle = np.full((2, rows, n_agents), np.nan)
    distance = np.full((2, rows, n_agents), np.nan)
    collisions_obstacle = np.full((2, rows, n_agents), np.nan)
    collisions_agent = np.full((2, rows, n_agents), np.nan)
    for k, length in enumerate(LENGTHS):
        t = np.arange(length + 1)[:, None]
        i = np.arange(n_agents)[None, :]
        positions[k, : length + 1, :, 0] = 2.0 + i + 0.5 * t + k
        positions[k, : length + 1, :, 1] = 3.0 + 0.25 * t + 0.3 * i * (i % 2)
        angle[k, 1 : length + 1] = (10.0 * t + i)[1:]
        distance[k, 1 : length + 1] = (0.1 * t * (i + 1))[1:]
        collisions_obstacle[k, 1 : length + 1] = 0.0
        collisions_agent[k, 1 : length + 1] = 0.0
    collisions_obstacle[OBSTACLE_HIT] = 1.0
    for hit in AGENT_HITS:
        collisions_agent[hit] = 1.0
    obstacles = np.array([[[8.0, 5.0, 0.5], [np.nan] * 3], [[6.0, 2.0, 0.8], [10.0, 7.0, 0.5]]])
    return Trajectories(
        config=config,
        episodes=np.array([0, 1]),
        seeds=np.array([100, 101]),
        lengths=np.array(LENGTHS),
        success=np.array([True, False]),
        goals=np.array([[12.0, 8.0], [13.0, 2.0]]),
        obstacles=obstacles,
        positions=positions,
        velocities=np.zeros_like(positions),
        actions=np.zeros_like(positions),
        angle_error_deg=angle,
        bearing_error=np.zeros_like(angle),
        neighbour_distance_error=distance,
        collisions_obstacle=collisions_obstacle,
        collisions_agent=collisions_agent,
        goal_distance=np.zeros((2, rows)),
    )


@pytest.fixture(scope="module")
def trajectories() -> Trajectories:
    return make_trajectories()


def assert_not_blank(figure: Figure, folder: Path) -> None:
    """The figure renders to a PNG with visible content (pixel variance well above a blank page's 0)."""
    path = save_figure(figure, folder / "check.png")
    with Image.open(path) as image:
        pixels = np.asarray(image.convert("L"), dtype=np.float64)
    assert pixels.var() > 100.0


# Trajectories --------------------------------------------------------------------------------------------------------


def test_trajectory_draws_the_world_paths_and_collisions(trajectories: Trajectories, tmp_path: Path) -> None:
    figure = plot_trajectory(trajectories, 0, every=2)
    assert_not_blank(figure, tmp_path)
    (ax,) = figure.axes
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")
    assert ax.get_title() == "episode 0 (seed 100): success, 6 steps"
    assert ax.get_xlim() == (0.0, 15.0) and ax.get_ylim() == (0.0, 10.0)
    assert ax.get_aspect() == 1.0
    renderer = figure.canvas.get_renderer()  # drawn by save_figure: the labels and the legend fit in the figure
    for artist in (ax.xaxis.label, ax.yaxis.label, ax.title, figure.legends[0]):
        box = artist.get_window_extent(renderer)
        assert box.x0 >= 0 and box.y0 >= 0 and box.x1 <= figure.bbox.x1 and box.y1 <= figure.bbox.y1
    paths = {line.get_label(): line for line in ax.get_lines() if line.get_label().startswith("agent")}
    assert sorted(paths) == ["agent 0", "agent 1", "agent 2"]
    for agent in range(3):
        np.testing.assert_array_equal(paths[f"agent {agent}"].get_xydata(), trajectories.positions[0, :7, agent])
    # the padded episode: its paths stop at its last step
    short = plot_trajectory(trajectories, 1).axes[0]
    assert short.get_title() == "episode 1 (seed 101): failure, 3 steps"
    line = next(line for line in short.get_lines() if line.get_label() == "agent 1")
    np.testing.assert_array_equal(line.get_xydata(), trajectories.positions[1, :4, 1])
    # collisions where they were placed
    markers = {collection.get_gid(): collection for collection in ax.collections if collection.get_gid()}
    episode, step, agent = OBSTACLE_HIT
    np.testing.assert_array_equal(markers["collisions_obstacle"].get_offsets(), [trajectories.positions[episode, step, agent]])
    expected = [trajectories.positions[hit] for hit in AGENT_HITS]
    np.testing.assert_array_equal(markers["collisions_agent"].get_offsets(), expected)
    assert "collisions_agent" not in {c.get_gid() for c in short.collections}  # the second episode had none
    # obstacles (the NaN row skipped) and the goal ring of radius eta_g
    circles = [patch for patch in ax.patches if isinstance(patch, Circle)]
    filled = [circle for circle in circles if circle.get_fill()]
    assert [(c.center, c.radius) for c in filled] == [((8.0, 5.0), 0.5)]
    (ring,) = [circle for circle in circles if not circle.get_fill()]
    assert ring.center == (12.0, 8.0) and ring.radius == trajectories.config.eta_g
    assert len([circle for circle in short.patches if isinstance(circle, Circle) and circle.get_fill()]) == 2
    legend = [text.get_text() for text in figure.legends[0].get_texts()]
    assert {"agent 0", "agent 1", "agent 2", "start", "end", "obstacle collision", "agent collision"} <= set(legend)


def test_a_lasting_contact_is_marked_once_where_it_begins(trajectories: Trajectories) -> None:
    touching = trajectories.collisions_obstacle.copy()
    touching[0, 2:5, 1] = 1.0  # agent 1 touches the obstacle in steps 2, 3 and 4
    touching[0, 6, 1] = 1.0  # and again in step 6
    figure = plot_trajectory(dataclasses.replace(trajectories, collisions_obstacle=touching), 0)
    markers = next(c for c in figure.axes[0].collections if c.get_gid() == "collisions_obstacle")
    np.testing.assert_array_equal(markers.get_offsets(), trajectories.positions[0, [2, 6], 1])


@pytest.mark.parametrize(("every", "steps"), [(1, [0, 1, 2, 3, 4, 5, 6]), (2, [0, 2, 4, 6]), (4, [0, 4, 6]), (25, [0, 6])])
def test_formation_polygon_is_drawn_every_few_steps_and_at_the_end(
    trajectories: Trajectories, every: int, steps: list[int]
) -> None:
    assert formation_steps(6, every) == steps
    ax = plot_trajectory(trajectories, 0, every=every).axes[0]
    polygons = [patch for patch in ax.patches if isinstance(patch, Polygon) and patch.get_gid() == "formation"]
    assert len(polygons) == len(steps)
    for polygon, step in zip(polygons, steps):
        vertices = polygon.get_xy()  # closed: the first vertex repeated at the end (ring 0 -> 1 -> 2 -> 0)
        np.testing.assert_allclose(vertices[:3], trajectories.positions[0, step])
        np.testing.assert_allclose(vertices[-1], trajectories.positions[0, step, 0])


def test_trajectory_rejects_bad_arguments(trajectories: Trajectories) -> None:
    with pytest.raises(IndexError, match="2 episodes"):
        plot_trajectory(trajectories, 2)
    with pytest.raises(ValueError, match="every"):
        plot_trajectory(trajectories, 0, every=0)
    assert plot_trajectory(trajectories, -1).axes[0].get_title().startswith("episode 1 ")


# Error curves --------------------------------------------------------------------------------------------------------


def test_error_curves_are_the_means_over_agents(trajectories: Trajectories, tmp_path: Path) -> None:
    figure = plot_error_curves(trajectories)
    assert_not_blank(figure, tmp_path)
    angle_ax, distance_ax = figure.axes
    assert angle_ax.get_ylabel() == "angle error (deg)" and distance_ax.get_ylabel() == "distance error (m)"
    assert distance_ax.get_xlabel() == "step" and angle_ax.get_title() and distance_ax.get_title()
    for k, length in enumerate(LENGTHS):
        step = np.arange(1, length + 1)
        angle = next(line for line in angle_ax.get_lines() if line.get_label() == f"episode {k}")
        distance = next(line for line in distance_ax.get_lines() if line.get_label() == f"episode {k}")
        np.testing.assert_array_equal(angle.get_xdata(), step)
        np.testing.assert_allclose(angle.get_ydata(), 10.0 * step + 1.0)  # mean of 10 t + i over i = 0, 1, 2
        np.testing.assert_allclose(distance.get_ydata(), 0.2 * step)  # mean of 0.1 t (i + 1)
    only = plot_error_curves(trajectories, indices=[1])
    assert [line.get_label() for line in only.axes[0].get_lines()] == ["episode 1"]
    with pytest.raises(ValueError, match="empty"):
        plot_error_curves(trajectories, indices=[])


# Evaluation bars -----------------------------------------------------------------------------------------------------


def summary(successes: list[bool], angle_errors: list[float]) -> dict:
    """An evaluation summary made the way ``evaluate`` makes it, from hand-made episode rows."""
    rows = [
        {
            "episode": k,
            "success": success,
            "angle_error_deg": angle_error,
            "bearing_error": 0.1 * k,
            "neighbour_distance_error": 0.05,
            "length": 100 + 10 * k,
            "collisions_obstacle": k % 2,
            "collisions_agent": 0,
            "comm_exceeded_fraction": 0.0,
        }
        for k, (success, angle_error) in enumerate(zip(successes, angle_errors))
    ]
    return EvaluationResult(rows, trajectories=None, stage=3, seed=0, deterministic=True, n_agents=3).summary


def bars(ax: Axes) -> list[BarContainer]:
    return [container for container in ax.containers if isinstance(container, BarContainer)]


def bar_heights(ax: Axes) -> dict[str, float]:
    return {container.get_label(): container.patches[0].get_height() for container in bars(ax)}


def test_evaluation_bars_show_the_summary_means(tmp_path: Path) -> None:
    summaries = {"individual": summary([True, True, False], [4.0, 8.0, 30.0]), "team": summary([False, False], [50.0, 60.0])}
    figure = plot_evaluation_bars(summaries)
    assert_not_blank(figure, tmp_path)
    axes = {ax.get_title(): ax for ax in figure.axes if ax.get_visible()}
    assert len(axes) == 8  # seven metrics and the success rate
    angle = axes["angle error"]
    assert angle.get_ylabel() == "angle error (deg)" and axes["neighbour-distance error"].get_ylabel() == "distance error (m)"
    assert axes["episode length"].get_ylabel() == "steps"
    assert bar_heights(angle) == {"individual": pytest.approx(6.0)}  # the team has no successful episode: no bar
    assert "no successful episodes" in [text.get_text() for text in angle.texts]
    assert bar_heights(axes["episode length"]) == {"individual": pytest.approx(105.0)}
    successful = summaries["individual"]["successful_episodes"]
    for title, key in [("bearing error", "bearing_error"), ("obstacle collisions", "collisions_obstacle")]:
        assert bar_heights(axes[title]) == {"individual": pytest.approx(successful[key]["mean"])}
    # the std error bar of the angle error: 6 +- 2
    (segment,) = bars(angle)[0].errorbar.lines[2][0].get_segments()
    np.testing.assert_allclose(segment[:, 1], [4.0, 8.0])
    rate = axes["success rate (95 % CI)"]
    assert bar_heights(rate) == {"individual": pytest.approx(2 / 3), "team": 0.0}
    for container, name in zip(bars(rate), summaries):
        (segment,) = container.errorbar.lines[2][0].get_segments()
        np.testing.assert_allclose(segment[:, 1], summaries[name]["success_rate_ci95"])
    legend = [text.get_text() for text in figure.legends[0].get_texts()]
    assert legend == ["individual", "team"]
    # over all episodes the team has bars too
    everything = {ax.get_title(): ax for ax in plot_evaluation_bars(summaries, over="all").axes}
    assert bar_heights(everything["angle error"]) == {"individual": pytest.approx(14.0), "team": pytest.approx(55.0)}
    assert not everything["angle error"].texts


def test_evaluation_bars_reject_an_unknown_grouping() -> None:
    with pytest.raises(ValueError, match="'best'"):
        plot_evaluation_bars({"a": summary([True], [1.0])}, over="best")
    with pytest.raises(ValueError, match="no summaries"):
        plot_evaluation_bars({})


# Training curves -----------------------------------------------------------------------------------------------------

N_STEPS, N_ENVS = 4, 2  # with ch4-individual's three agents: 24 steps per iteration


def write_run(folder: Path, seed: int, rewards: dict[int, float], success: dict[int, float], start: float = 1000.0) -> Path:
    """A run folder with config.yaml (as ``train`` writes it) and TensorBoard events at step = iteration x 24."""
    settings = layered_settings(recipe="ch4-individual", seed=seed, n_envs=N_ENVS, ppo={"n_steps": N_STEPS})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(settings.to_dict(), sort_keys=False))
    add_events(folder, rewards, success, start)
    return folder


def add_events(folder: Path, rewards: dict[int, float], success: dict[int, float], start: float) -> None:
    """One more event file (one training session), its events at wall times start, start + 1, ..."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(log_dir=str(folder / "tensorboard"), filename_suffix=f".{start:.0f}")
    for offset, (iteration, value) in enumerate(rewards.items()):
        writer.add_scalar("rollout/ep_rew_mean", value, global_step=iteration * 24, walltime=start + offset)
        writer.add_scalar("train/value_loss", 1.0, global_step=iteration * 24, walltime=start + offset)
    for offset, (iteration, value) in enumerate(success.items()):
        writer.add_scalar("episode/success_rate", value, global_step=iteration * 24, walltime=start + offset)
    writer.close()


def test_training_curves_are_read_per_iteration_and_a_resume_keeps_the_last_values(tmp_path: Path) -> None:
    run = write_run(tmp_path / "run", 0, {1: -5.0, 2: -4.0, 3: -3.0}, {1: 0.0, 2: 0.5, 3: 0.25})
    assert steps_per_iteration(run) == N_STEPS * N_ENVS * 3
    curves = load_training_curves(run)
    assert sorted(curves) == ["episode_reward", "success_rate"]
    np.testing.assert_array_equal(curves["episode_reward"][0], [1, 2, 3])
    np.testing.assert_array_equal(curves["episode_reward"][1], [-5.0, -4.0, -3.0])
    np.testing.assert_array_equal(curves["success_rate"][1], [0.0, 0.5, 0.25])
    # resumed from the checkpoint of iteration 2: iteration 3 is logged again, later, and its new value wins
    add_events(run, {3: -2.0, 4: -1.0}, {3: 0.75, 4: 1.0}, start=2000.0)
    assert len(list((run / "tensorboard").glob("events.out.tfevents.*"))) == 2
    curves = load_training_curves(run)
    np.testing.assert_array_equal(curves["episode_reward"][0], [1, 2, 3, 4])
    np.testing.assert_array_equal(curves["episode_reward"][1], [-5.0, -4.0, -2.0, -1.0])
    np.testing.assert_array_equal(curves["success_rate"][1], [0.0, 0.5, 0.75, 1.0])


def test_missing_training_logs_are_errors_naming_the_folder(tmp_path: Path) -> None:
    empty = tmp_path / "empty_run"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="empty_run has no tensorboard folder"):
        load_training_curves(empty)
    (empty / "tensorboard").mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty_run.tensorboard holds no TensorBoard event file"):
        load_training_curves(empty)
    other = write_run(tmp_path / "other_run", 0, {}, {})
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(log_dir=str(other / "tensorboard")) as writer:
        writer.add_scalar("train/loss", 1.0, global_step=24)
    with pytest.raises(ValueError, match="other_run hold none of the scalars"):
        load_training_curves(other)


def test_rolling_mean_is_a_trailing_mean_over_iterations() -> None:
    x, y = np.array([1.0, 2.0, 3.0, 4.0, 5.0]), np.array([1.0, 2.0, 6.0, 4.0, 5.0])
    # window 3: [1], [1, 2], [1, 2, 6], [2, 6, 4], [6, 4, 5]
    np.testing.assert_allclose(rolling_mean(x, y, 3), [1.0, 1.5, 3.0, 4.0, 5.0])
    # a missing iteration shortens the window: at 5 only iterations 3 and 5 are within the last 3
    np.testing.assert_allclose(rolling_mean(np.array([1.0, 3.0, 5.0]), np.array([2.0, 4.0, 8.0]), 3), [2.0, 3.0, 6.0])
    np.testing.assert_allclose(rolling_mean(x, y, 1), y)
    with pytest.raises(ValueError, match="window"):
        rolling_mean(x, y, 0)


def test_training_curves_average_seeds_with_a_std_band(tmp_path: Path) -> None:
    rewards = [{1: 1.0, 2: 3.0, 3: 5.0, 4: 4.0, 5: 9.0}, {1: 2.0, 2: 2.0, 3: 8.0, 4: 0.0, 5: 1.0, 6: 7.0}]
    success = [{k: v / 10 for k, v in reward.items()} for reward in rewards]
    seeds = [write_run(tmp_path / f"a_s{seed}", seed, rewards[seed], success[seed]) for seed in (0, 1)]
    single = write_run(tmp_path / "b_s0", 0, {1: -1.0, 2: -2.0}, {1: 0.0, 2: 1.0})
    figure = plot_training_curves({"A": seeds, "B": [single]}, window=3)
    assert_not_blank(figure, tmp_path)
    reward_ax, success_ax = figure.axes
    assert success_ax.get_xlabel() == "iteration"
    assert reward_ax.get_ylabel() == "mean episode reward" and success_ax.get_ylabel() == "success rate"
    assert "rolling mean over 3 iterations" in reward_ax.get_title()
    labels = [text.get_text() for text in reward_ax.get_legend().get_texts()]
    assert labels == ["A (2 seeds)", "B (1 seed)"]
    shared = np.arange(1.0, 6.0)  # seed 1's iteration 6 is not shared
    smoothed = np.stack([rolling_mean(np.array(list(r)), np.array(list(r.values())), 3)[:5] for r in rewards])
    mean, std = smoothed.mean(axis=0), smoothed.std(axis=0)
    for ax, scale, single_curve in ((reward_ax, 1.0, [-1.0, -1.5]), (success_ax, 0.1, [0.0, 0.5])):
        lines = {line.get_label(): line for line in ax.get_lines()}
        np.testing.assert_array_equal(lines["A (2 seeds)"].get_xdata(), shared)
        np.testing.assert_allclose(lines["A (2 seeds)"].get_ydata(), scale * mean)
        np.testing.assert_allclose(lines["B (1 seed)"].get_ydata(), single_curve)
        (band,) = [collection for collection in ax.collections if isinstance(collection, PolyCollection)]  # A only
        vertices = band.get_paths()[0].vertices
        for x, low, high in zip(shared, scale * (mean - std), scale * (mean + std)):
            at_x = vertices[np.isclose(vertices[:, 0], x), 1]
            assert np.isclose(at_x, low).any() and np.isclose(at_x, high).any()
        assert vertices[:, 1].min() == pytest.approx(np.min(scale * (mean - std)))
        assert vertices[:, 1].max() == pytest.approx(np.max(scale * (mean + std)))
    alone = plot_training_curves({"B": [single]}, window=3)
    assert not [c for ax in alone.axes for c in ax.collections if isinstance(c, PolyCollection)]
    with pytest.raises(FileNotFoundError, match="missing_run"):
        plot_training_curves({"C": [tmp_path / "missing_run"]})


# Saving --------------------------------------------------------------------------------------------------------------


def test_save_figure_writes_png_svg_and_pdf_atomically(trajectories: Trajectories, tmp_path: Path) -> None:
    figure = plot_error_curves(trajectories)
    folder = tmp_path / "figures" / "nested"
    png = save_figure(figure, folder / "errors.png")
    with Image.open(png) as image:
        assert image.format == "PNG"
    assert save_figure(figure, folder / "errors") == folder / "errors.png"
    assert b"<svg" in save_figure(figure, folder / "errors.svg").read_bytes()[:500]
    assert save_figure(figure, folder / "errors.PDF").read_bytes().startswith(b"%PDF")
    assert sorted(path.name for path in folder.iterdir()) == ["errors.PDF", "errors.png", "errors.svg"]  # no leftovers
    with pytest.raises(ValueError, match="'jpg'"):
        save_figure(figure, tmp_path / "x.jpg")
    assert not (tmp_path / "x.jpg").exists()
