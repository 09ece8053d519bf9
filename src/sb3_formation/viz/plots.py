"""Thesis-style figures with matplotlib: trajectories, error curves, evaluation bars and training curves.

Every function returns a :class:`matplotlib.figure.Figure` drawn on its own Agg canvas (no ``pyplot``, no global
state); write it with :func:`save_figure`. Figure numbers refer to the thesis: trajectories 4.7/4.8 and 5.7-5.10,
error curves 4.9/4.10 and 5.11/5.12, evaluation bars 4.6/5.6, training curves 4.4/4.5 and 5.4/5.5.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Polygon

from sb3_formation.env.rendering import AGENT_COLOURS
from sb3_formation.experiment.recipes import load_settings
from sb3_formation.experiment.sweep import SweepResult
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.sb3.metrics import EPISODE_METRICS, SUCCESS_RATE_TAG
from sb3_formation.utils.files import atomic_files

#: Colours of agents (agent i: colour i mod 10) and of policies or recipes in comparisons: matplotlib's tab10.
COLOURS: tuple[tuple[float, float, float], ...] = tuple((r / 255, g / 255, b / 255) for r, g, b in AGENT_COLOURS)
#: TensorBoard scalar tag -> name of the curve returned by :func:`load_training_curves`.
TRAINING_SCALARS: dict[str, str] = {"rollout/ep_rew_mean": "episode_reward", SUCCESS_RATE_TAG: "success_rate"}
#: Curve name -> y-axis label in :func:`plot_training_curves`.
TRAINING_LABELS: dict[str, str] = {"episode_reward": "mean episode reward", "success_rate": "success rate"}
#: File formats :func:`save_figure` writes.
FIGURE_FORMATS = ("png", "svg", "pdf")
#: Figure names of ``sb3-formation plot``.
PNG_DPI = 150
OBSTACLE_COLOUR, GOAL_COLOUR = (0.55, 0.55, 0.59), (0.16, 0.67, 0.27)


def _new_figure(figsize: tuple[float, float]) -> Figure:
    """A figure with constrained layout on its own Agg canvas."""
    figure = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _colour(index: int) -> tuple[float, float, float]:
    return COLOURS[index % len(COLOURS)]


def _episode_row(trajectories: Trajectories, index: int) -> int:
    """Check ``index`` against the recorded episodes (negative indices count from the end)."""
    count = len(trajectories)
    if not -count <= index < count:
        raise IndexError(f"episode index {index} is out of range: {count} episodes are recorded")
    return index % count


# Trajectories -------------------------------------------------------------------------------------------------------


def formation_steps(length: int, every: int) -> list[int]:
    """Steps at which :func:`plot_trajectory` draws the formation polygon: 0, every, 2 every, ... and the last step.

    :param length: steps played (the last row is ``length``)
    :param every: steps between two polygons (>= 1)
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    steps = list(range(0, length + 1, every))
    return steps if steps[-1] == length else [*steps, length]


def _wall_patches(wall: np.ndarray) -> list[Patch]:
    """A wall (x0, y0, x1, y1, thickness) as the patches of its capsule: the rectangle and the two end discs."""
    ends, radius = wall[:4].reshape(2, 2), wall[4] / 2
    along = ends[1] - ends[0]
    normal = np.array([-along[1], along[0]]) / max(float(np.hypot(*along)), 1e-12) * radius
    corners = [ends[0] + normal, ends[1] + normal, ends[1] - normal, ends[0] - normal]
    patches: list[Patch] = [Polygon(corners, closed=True, facecolor=OBSTACLE_COLOUR, edgecolor="none", zorder=1)]
    patches += [Circle(tuple(end), radius, facecolor=OBSTACLE_COLOUR, edgecolor="none", zorder=1) for end in ends]
    for patch in patches:
        patch.set_gid("wall")
    return patches


def plot_trajectory(trajectories: Trajectories, index: int, every: int = 25) -> Figure:
    """One episode to scale: obstacles and walls, the goal ring, each agent's path, the formation every ``every`` steps, and a
    mark where an agent's contact with an obstacle (red x) or another agent (black +) begins.

    :param trajectories: recorded evaluation episodes
    :param index: which recorded episode (row of the arrays, not the evaluation episode number)
    :param every: steps between two drawings of the formation polygon (ring order 0 -> 1 -> ... -> n - 1 -> 0)
    """
    row = _episode_row(trajectories, index)
    config = trajectories.config
    steps = trajectories.steps(row)
    positions = steps["positions"]  # (T + 1, n, 2)
    length, n_agents = len(positions) - 1, positions.shape[1]
    polygon_steps = formation_steps(length, every)
    width, height = config.world_width, config.world_height
    figure = _new_figure((7.0 * width / max(width, height) + 3.6, 7.0 * height / max(width, height) + 0.8))
    ax = figure.add_subplot()
    ax.set_xlim(0.0, width)
    ax.set_ylim(0.0, height)
    ax.set_aspect("equal")
    for spine in ax.spines.values():  # the walls
        spine.set_linewidth(2.5)
        spine.set_color((0.24, 0.24, 0.24))
    for x, y, radius in trajectories.obstacles[row]:
        if not np.isnan([x, y, radius]).any():
            ax.add_patch(Circle((x, y), radius, facecolor=OBSTACLE_COLOUR, edgecolor="none", zorder=1))
    for wall in trajectories.walls[row]:
        if not np.isnan(wall).any():
            for patch in _wall_patches(wall):
                ax.add_patch(patch)
    goal = trajectories.goals[row]
    ax.add_patch(Circle(tuple(goal), config.eta_g, fill=False, edgecolor=GOAL_COLOUR, linestyle="--", linewidth=1.5))
    ax.plot(*goal, marker="*", color=GOAL_COLOUR, markersize=10, linestyle="none")
    for step in polygon_steps:
        vertices = positions[step]  # the ring 0 -> 1 -> ... -> n - 1 -> 0
        polygon = Polygon(vertices, closed=True, fill=False, edgecolor="black", linewidth=0.8, alpha=0.35, zorder=2)
        polygon.set_gid("formation")
        ax.add_patch(polygon)
    handles: list[Any] = []
    for agent in range(n_agents):
        (line,) = ax.plot(positions[:, agent, 0], positions[:, agent, 1], color=_colour(agent), linewidth=1.2, zorder=3)
        line.set_label(f"agent {agent}")
        handles.append(line)
    starts, ends = positions[0], positions[-1]
    colours = [_colour(agent) for agent in range(n_agents)]
    ax.scatter(starts[:, 0], starts[:, 1], s=30, facecolors="white", edgecolors=colours, linewidths=1.5, zorder=4)
    ax.scatter(ends[:, 0], ends[:, 1], s=30, marker="s", c=colours, edgecolors="black", linewidths=0.6, zorder=4)
    handles += [
        Line2D([], [], marker="o", color="black", markerfacecolor="white", linestyle="none", label="start"),
        Line2D([], [], marker="s", color="black", linestyle="none", label="end"),
        Line2D([], [], color="black", alpha=0.35, linewidth=0.8, label=f"formation (every {every} steps)"),
        Patch(facecolor=OBSTACLE_COLOUR, label="obstacle"),
        Line2D([], [], color=GOAL_COLOUR, linestyle="--", marker="*", label=f"goal (radius {config.eta_g:g} m)"),
    ]
    collisions = (
        ("collisions_obstacle", "x", "red", "obstacle collision"),
        ("collisions_agent", "+", "black", "agent collision"),
    )
    for name, marker, colour, label in collisions:
        touching = np.nan_to_num(steps[name], nan=0.0) > 0
        onsets = touching & ~np.vstack([np.zeros((1, n_agents), dtype=bool), touching[:-1]])  # a long touch: one mark
        hit_rows, hit_agents = np.nonzero(onsets)
        if len(hit_rows):
            points = positions[hit_rows, hit_agents]
            markers = ax.scatter(points[:, 0], points[:, 1], marker=marker, color=colour, s=50, linewidths=1.5, zorder=5)
            markers.set_gid(name)
            markers.set_label(label)
            handles.append(markers)
    figure.legend(handles=handles, loc="outside right upper", fontsize="small", frameon=False)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    outcome = "success" if trajectories.success[row] else "failure"
    ax.set_title(f"episode {int(trajectories.episodes[row])} (seed {int(trajectories.seeds[row])}): {outcome}, {length} steps")
    return figure


def plot_error_curves(trajectories: Trajectories, indices: Sequence[int] | None = None) -> Figure:
    """Mean (over agents) angle error and neighbour-distance error against the step, one line per episode.

    :param trajectories: recorded evaluation episodes
    :param indices: which recorded episodes (rows of the arrays; default: all)
    """
    rows = [_episode_row(trajectories, index) for index in (range(len(trajectories)) if indices is None else indices)]
    if not rows:
        raise ValueError("no episodes to plot: indices is empty")
    figure = _new_figure((8.0, 6.0))
    angle_ax, distance_ax = figure.subplots(2, 1, sharex=True)
    for colour_index, row in enumerate(rows):
        steps = trajectories.steps(row)
        step = np.arange(1, len(steps["positions"]))  # row 0 is the state after reset: no error yet
        label, colour = f"episode {int(trajectories.episodes[row])}", _colour(colour_index)
        angle_ax.plot(step, steps["angle_error_deg"][1:].mean(axis=1), color=colour, linewidth=1.0, label=label)
        distance_ax.plot(step, steps["neighbour_distance_error"][1:].mean(axis=1), color=colour, linewidth=1.0, label=label)
    angle_ax.set_title("mean angle error over the agents")
    angle_ax.set_ylabel("angle error (deg)")
    distance_ax.set_title("mean neighbour-distance error over the agents (distances beyond $d_{ref}$)")
    distance_ax.set_ylabel("distance error (m)")
    distance_ax.set_xlabel("step")
    for ax in (angle_ax, distance_ax):
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
    angle_ax.legend(fontsize="small", ncols=min(len(rows), 5))
    return figure


# Evaluation summaries ------------------------------------------------------------------------------------------------


def _summary_value(summaries: Mapping[str, dict], policy: str, *keys: str) -> Any:
    """``summaries[policy][keys[0]][keys[1]]...`` or a ``ValueError`` naming the policy and the missing key."""
    value: Any = summaries[policy]
    for key in keys:
        if not isinstance(value, Mapping) or key not in value:
            raise ValueError(f"the summary of {policy!r} has no {'/'.join(keys)}: is it an evaluation summary.json?")
        value = value[key]
    return value


def plot_evaluation_bars(summaries: Mapping[str, dict], over: str = "successful") -> Figure:
    """Compare evaluations: one axes per metric with a bar (mean +- std) per policy, plus the success rate.

    The metrics are those of :data:`~sb3_formation.env.episodes.EPISODE_METRICS` found in the summaries; a policy
    without episodes to average (``None`` means) gets a note instead of a bar. The success rate (over all episodes) has
    its 95 % Wilson interval as error bar.

    :param summaries: policy label -> evaluation summary (``EvaluationResult.summary`` or ``eval/summary.json``)
    :param over: ``"successful"`` (means over the successful episodes, as in the thesis) or ``"all"`` episodes
    """
    groups = {"successful": "successful_episodes", "all": "all_episodes"}
    if over not in groups:
        raise ValueError(f"over must be 'successful' or 'all', got {over!r}")
    if not summaries:
        raise ValueError("no summaries to plot")
    policies = list(summaries)
    group = groups[over]
    metrics = [name for name in EPISODE_METRICS if any(name in (summaries[p].get(group) or {}) for p in policies)]
    n_axes = len(metrics) + 1
    n_columns = min(4, n_axes)
    n_rows = math.ceil(n_axes / n_columns)
    figure = _new_figure((2.8 * n_columns + 0.5, 2.6 * n_rows + 0.6))
    axes = figure.subplots(n_rows, n_columns, squeeze=False).ravel()
    positions = np.arange(len(policies))
    missing = "no successful episodes" if over == "successful" else "no episodes"
    for ax, name in zip(axes, metrics):
        for position, policy in zip(positions, policies):
            statistics = (summaries[policy].get(group) or {}).get(name) or {}
            mean, std = statistics.get("mean"), statistics.get("std")
            if mean is None:
                ax.text(position, 0.0, missing, rotation=90, ha="center", va="bottom", fontsize="x-small", color="dimgray")
                continue
            yerr = None if std is None else [[std], [std]]
            ax.bar(position, mean, yerr=yerr, color=_colour(int(position)), capsize=3, width=0.7, label=policy)
        title, ylabel = EPISODE_METRICS[name].title, EPISODE_METRICS[name].axis
        ax.set_ylim(bottom=0.0)  # every metric is >= 0
        ax.set_title(title)
        ax.set_ylabel(ylabel)
    ax = axes[len(metrics)]
    for position, policy in zip(positions, policies):
        rate = float(_summary_value(summaries, policy, "success_rate"))
        low, high = (float(bound) for bound in _summary_value(summaries, policy, "success_rate_ci95"))
        yerr = [[max(rate - low, 0.0)], [max(high - rate, 0.0)]]
        ax.bar(position, rate, yerr=yerr, color=_colour(int(position)), capsize=3, width=0.7, label=policy)
    ax.set_ylim(0.0, 1.05)
    ax.set_title("success rate (95 % CI)")
    ax.set_ylabel("success rate")
    for ax in axes[:n_axes]:
        ax.set_xticks(positions, [""] * len(policies))
        ax.set_xlim(-0.6, len(policies) - 0.4)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[n_axes:]:
        ax.set_visible(False)
    handles = [Patch(facecolor=_colour(position), label=policy) for position, policy in enumerate(policies)]
    figure.legend(handles=handles, loc="outside lower center", ncols=min(len(policies), 4), frameon=False)
    figure.suptitle(f"evaluation: means and std over {over} episodes")
    return figure


# Robustness curves ---------------------------------------------------------------------------------------------------


def plot_robustness(rows: Sequence[Mapping[str, Any]], scenes: str | None = None) -> Figure:
    """Robustness curves of one scene set: success, the share of episodes with contacts and the shape error against
    the disturbance level, a column each, a row of panels per factor (all parts, then each part alone), one line per
    target with its 95 % interval as a band; a dotted line marks level 1, the profile itself.

    :param rows: the sweep's rows (:meth:`~sb3_formation.experiment.robustness.RobustnessRow.cells`, or the ``rows``
        of ``robustness.json``)
    :param scenes: the scene set drawn (default: the one the rows have)
    :raises ValueError: no rows of ``scenes``, or rows of several scene sets and no ``scenes``
    """
    sets = list(dict.fromkeys(row["scenes"] for row in rows))
    if scenes is None:
        if len(sets) != 1:
            raise ValueError(f"the rows are of {len(sets)} scene sets {sets}: name the one to draw")
        scenes = sets[0]
    chosen = [row for row in rows if row["scenes"] == scenes]
    if not chosen:
        raise ValueError(f"no rows of the scene set {scenes!r} to plot; the rows have {sets}")
    panels = (  # a row's value, its 95 % interval, the panel's title and its y-axis
        ("success_rate", "success_rate_ci95", "success", "success rate"),
        ("contact_rate", "contact_rate_ci95", "episodes with contacts", "share of episodes"),
        ("shape_error", "shape_error_ci95", "shape error over successes", "bearing error"),
    )
    factors = list(dict.fromkeys(row["factor"] for row in chosen))
    targets = list(dict.fromkeys(row["target"] for row in chosen))
    figure = _new_figure((4.0 * len(panels) + 0.4, 2.7 * len(factors) + 1.0))
    axes = figure.subplots(len(factors), len(panels), squeeze=False, sharex=True, sharey="col")
    levels = sorted({float(row["level"]) for row in chosen})
    for factor_axes, factor in zip(axes, factors):
        for ax, (value, interval, title, ylabel) in zip(factor_axes, panels):
            for index, target in enumerate(targets):
                points = sorted(
                    (row for row in chosen if row["factor"] == factor and row["target"] == target),
                    key=lambda row: float(row["level"]),
                )
                x = np.array([float(row["level"]) for row in points])
                y = np.array([np.nan if row[value] is None else float(row[value]) for row in points])
                bounds = np.array([[np.nan, np.nan] if row[interval] is None else row[interval] for row in points])
                colour = _colour(index)
                ax.plot(x, y, color=colour, marker="o", markersize=3.5, linewidth=1.2, label=target)
                if len(points):
                    ax.fill_between(x, bounds[:, 0], bounds[:, 1], color=colour, alpha=0.2, linewidth=0)
            if levels[0] <= 1.0 <= levels[-1]:
                ax.axvline(1.0, color="dimgray", linestyle=":", linewidth=1.0)
            if value != "shape_error":
                ax.set_ylim(-0.02, 1.05)
            ax.set_title(f"{'all parts' if factor == 'all' else factor}: {title}", fontsize="medium")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
    axes[0][-1].set_ylim(bottom=0.0)  # once every factor's errors are drawn (the column shares its axis)
    for ax in axes[-1]:
        ax.set_xlabel("disturbance level (1: the profile)")
        if len(levels) <= 10:
            ax.set_xticks(levels, [f"{level:g}" for level in levels])
    handles = [Line2D([], [], color=_colour(index), marker="o", label=target) for index, target in enumerate(targets)]
    figure.legend(handles=handles, loc="outside lower center", ncols=min(len(targets), 4), frameon=False)
    figure.suptitle(f"robustness on {scenes}: {chosen[0]['episodes']} episodes a point, bands 95 % intervals")
    return figure


# Training curves -----------------------------------------------------------------------------------------------------


def steps_per_iteration(run_dir: Path) -> int:
    """Environment steps logged per PPO iteration of a run: n_steps x the agents of every team, from its config.yaml."""
    return load_settings(Path(run_dir)).recipe.steps_per_iteration()


def _read_scalars(event_file: Path) -> dict[str, list[tuple[float, int, float]]]:
    """(wall time, step, value) of every scalar of one TensorBoard event file, by tag."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(event_file), size_guidance={"scalars": 0}, purge_orphaned_data=False)
    accumulator.Reload()
    return {
        tag: [(event.wall_time, event.step, event.value) for event in accumulator.Scalars(tag)]
        for tag in accumulator.Tags()["scalars"]
    }


def load_training_curves(run_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The episode reward and success rate a run logged to TensorBoard, against the PPO iteration.

    Every event file under ``<run_dir>/tensorboard`` is read (a resumed run adds files); a step logged more than once
    (a resume re-logs the iterations after its checkpoint) keeps its latest value by wall time.

    :param run_dir: a run folder (with ``config.yaml`` and ``tensorboard/``)
    :return: ``"episode_reward"`` (``rollout/ep_rew_mean``) and ``"success_rate"`` (``episode/success_rate``), those
        logged, each as (iterations, values) sorted by iteration; iteration = logged step / :func:`steps_per_iteration`
    """
    run_dir = Path(run_dir)
    folder = run_dir / "tensorboard"
    if not folder.is_dir():
        raise FileNotFoundError(f"{run_dir} has no tensorboard folder: is it a training run folder?")
    event_files = sorted(path for path in folder.rglob("events.out.tfevents.*") if path.is_file())
    if not event_files:
        raise FileNotFoundError(f"{folder} holds no TensorBoard event file (events.out.tfevents.*)")
    events: dict[str, list[tuple[float, int, int, float]]] = {tag: [] for tag in TRAINING_SCALARS}
    for order, event_file in enumerate(event_files):
        for tag, scalars in _read_scalars(event_file).items():
            if tag in events:
                events[tag].extend((wall_time, order, step, value) for wall_time, step, value in scalars)
    if not any(events.values()):
        raise ValueError(f"the TensorBoard events of {run_dir} hold none of the scalars {sorted(TRAINING_SCALARS)}")
    per_iteration = steps_per_iteration(run_dir)
    curves: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for tag, name in TRAINING_SCALARS.items():
        if not events[tag]:
            continue
        latest: dict[int, float] = {}
        for _, _, step, value in sorted(events[tag], key=lambda event: (event[0], event[1])):  # stable: file order
            latest[step] = value
        steps = np.array(sorted(latest), dtype=np.float64)
        curves[name] = (steps / per_iteration, np.array([latest[int(step)] for step in steps], dtype=np.float64))
    return curves


def rolling_mean(x: np.ndarray, y: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean of ``y`` over the points with ``x`` in (x_i - window, x_i] (all there are at the start).

    :param x: increasing iterations
    :param y: values at ``x``
    :param window: width of the window, in iterations (>= 1)
    """
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    sums = np.concatenate([[0.0], np.cumsum(y)])
    first = np.searchsorted(x, x - window, side="right")
    last = np.arange(1, len(x) + 1)
    return (sums[last] - sums[first]) / (last - first)


def plot_training_curves(runs: Mapping[str, Sequence[Path]], window: int = 100) -> Figure:
    """Episode reward and success rate against the iteration, averaged over the seeds of each recipe.

    Each run's curve is smoothed with :func:`rolling_mean`; a label with several runs is drawn as the mean over its
    runs with a band of +- one (population) std, over the iterations all of its runs logged.

    :param runs: label (a recipe) -> its run folders (one per seed)
    :param window: smoothing window (iterations)
    """
    if not runs:
        raise ValueError("no runs to plot")
    empty = [label for label, folders in runs.items() if not folders]
    if empty:
        raise ValueError(f"no run folders given for {empty}")
    figure = _new_figure((8.0, 6.5))
    axes = dict(zip(TRAINING_LABELS, figure.subplots(2, 1, sharex=True)))
    for label_index, (label, folders) in enumerate(runs.items()):
        colour = _colour(label_index)
        loaded = [load_training_curves(Path(folder)) for folder in folders]
        seeds = "1 seed" if len(folders) == 1 else f"{len(folders)} seeds"
        for name, ax in axes.items():
            curves = [(x, rolling_mean(x, y, window)) for x, y in (curve[name] for curve in loaded if name in curve)]
            if not curves:
                continue
            if len(curves) == 1:
                ax.plot(*curves[0], color=colour, linewidth=1.2, label=f"{label} ({seeds})")
                continue
            shared = curves[0][0]
            for x, _ in curves[1:]:
                shared = np.intersect1d(shared, x)
            if not len(shared):
                raise ValueError(f"the runs of {label!r} share no logged iteration of {name}")
            values = np.stack([y[np.isin(x, shared)] for x, y in curves])
            mean, std = values.mean(axis=0), values.std(axis=0)
            ax.plot(shared, mean, color=colour, linewidth=1.2, label=f"{label} ({seeds})")
            ax.fill_between(shared, mean - std, mean + std, color=colour, alpha=0.2, linewidth=0)
    for name, ax in axes.items():
        ax.set_ylabel(TRAINING_LABELS[name])
        ax.grid(alpha=0.3)
    axes["episode_reward"].set_title(f"episode reward (rolling mean over {window} iterations)")
    axes["success_rate"].set_title(f"success rate (rolling mean over {window} iterations)")
    axes["success_rate"].set_xlabel("iteration")
    axes["episode_reward"].legend(fontsize="small")
    return figure


# Saving ---------------------------------------------------------------------------------------------------------------


def save_figure(figure: Figure, path: Path) -> Path:
    """Write ``figure`` atomically (temporary file, then rename) in the format of the path's suffix.

    :param figure: the figure
    :param path: target file; its suffix picks the format: ``.png`` (150 dpi; added when there is no suffix), ``.svg``
        or ``.pdf``. Parent folders are created.
    :return: the file written
    """
    return save_figures({path: figure})[0]


def save_figures(figures: Mapping[Path, Figure]) -> list[Path]:
    """Write a set of figures into one folder as one unit: all of them replace their files, or (on any failure, a full
    disk included) none does; two sets written into one folder at once follow each other (see
    :func:`~sb3_formation.utils.files.atomic_files`).

    :param figures: target file -> figure; a file's suffix picks its format as in :func:`save_figure`
    :return: the files written, in the order of ``figures``
    """
    targets = {_figure_path(path): figure for path, figure in figures.items()}
    contents = {path: _encode(figure, path) for path, figure in targets.items()}
    folders = {path.parent for path in contents}
    if len(folders) != 1:
        raise ValueError(f"a figure set goes into one folder, got {len(folders)}: {', '.join(map(str, sorted(folders)))}")
    folder = folders.pop()
    with atomic_files(folder, [path.name for path in contents], what="figure folder") as temporaries:
        for path, data in contents.items():
            temporaries[path.name].write_bytes(data)
    return list(contents)


def _figure_path(path: str | Path) -> Path:
    """The file a figure goes to: ``path``, with ``.png`` added when it has no suffix.

    :raises ValueError: the suffix is not one of :data:`FIGURE_FORMATS`
    """
    path = Path(path)
    if not path.suffix:
        path = path.with_name(path.name + ".png")
    if path.suffix[1:].lower() not in FIGURE_FORMATS:
        raise ValueError(f"cannot save a figure as {path.suffix[1:]!r} ({path}): use one of {', '.join(FIGURE_FORMATS)}")
    return path


def _encode(figure: Figure, path: Path) -> bytes:
    """The bytes of ``figure`` in the format of ``path``'s suffix (PNG at :data:`PNG_DPI` dpi)."""
    file_format = path.suffix[1:].lower()
    buffer = io.BytesIO()
    figure.savefig(buffer, format=file_format, dpi=PNG_DPI if file_format == "png" else "figure")
    return buffer.getvalue()


def save_sweep_curves(result: SweepResult) -> Path | None:
    """Draw a sweep's training curves (mean over its seeds with a +-1 std band) to ``training_curves.png`` in its
    folder; ``None`` when no trial finished."""
    if not result.run_dirs:
        return None
    return save_figure(plot_training_curves({result.label: result.run_dirs}), result.folder / "training_curves.png")
