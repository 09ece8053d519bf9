"""Robustness curves: what a policy keeps of its success, its safety and its shape as the world's errors grow.

Protocol (``sb3-formation robustness``): the benchmark's (:mod:`~sb3_formation.experiment.benchmark`: stage 3, each
scene set of :data:`~sb3_formation.env.scenes.BENCHMARK_SCENES`, episode k from ``reset(seed=seed + k)`` from the
held-out seed 10,000, deterministic actions, 100 episodes), played once per point of a sweep over a disturbance
profile's level: the profile scaled by each level (:meth:`~sb3_formation.env.disturbances.Disturbances.scaled`; 0 is
the ideal world, 1 the profile, 2 twice its errors). With factors, each part of the profile that it disturbs is swept
alone too (:meth:`~sb3_formation.env.disturbances.Disturbances.only`: ``sensing``, ``acting``, ``timing``,
``communication``), beside ``all`` of them together: which error costs what. Level 0 is the same ideal world for every
factor: it is played once per target and scene set, and its evaluation files are written under every factor.

Every point's episodes meet the same scenarios (the seeds), so the curves differ by the disturbances alone. A row
reports, besides the benchmark's figures (:meth:`~sb3_formation.experiment.benchmark.BenchmarkRow.cells`):

- ``success_rate`` with its Wilson 95 % interval;
- ``contact_rate``: the share of episodes with any contact (between agents, or with an obstacle or the border), with
  its Wilson 95 % interval (``episodes_with_contacts`` counts them);
- ``shape_error``: the bearing error averaged over the successful episodes (the benchmark's), with a 95 % interval of
  that mean: 1.96 standard errors either side, at least 0 (a normal approximation, narrow when few episodes succeed;
  none below two successes);
- ``folder``: where its evaluation files are, inside the sweep's folder (``<label>/<factor>/<level>/<scenes>``).

``robustness.md`` opens with the run's provenance (date, CPU, cores, package version, command, protocol, profile),
then the table; ``robustness.json`` holds the same as data (``run`` and ``rows``; :func:`read_robustness` reads it).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sb3_formation import __version__
from sb3_formation.env.disturbances import PARTS, Disturbances, disturbance_label, load_disturbances
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.benchmark import BENCHMARK_EPISODES, BENCHMARK_SEED, BenchmarkRow
from sb3_formation.experiment.evaluation import EvaluationResult, evaluate_target
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.checks import check_name, is_number
from sb3_formation.utils.files import LOCK_FILE, atomic_write, holds_files, read_json
from sb3_formation.utils.machine import machine_line

#: The levels a sweep plays by default: the ideal world, a quarter, half, the profile, one and a half and twice it.
ROBUSTNESS_LEVELS: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0)
#: The largest level: ten times the profile's errors (probabilities reach 1 and gains their floor well before).
MAX_LEVEL = 10.0
#: The most levels one sweep plays (each is a full benchmark per factor).
MAX_LEVELS = 20
#: The factor of every part of the profile together; the others are the parts' names (:data:`PARTS`).
ALL_PARTS = "all"
#: The standard-normal quantile of the shape error's 95 % interval.
Z95 = 1.959963984540054
TABLE_FILE, RESULTS_FILE = "robustness.md", "robustness.json"
#: The folder of a sweep's figures (``sb3-formation robustness`` draws them there).
FIGURES_FOLDER = "figures"


@dataclass(frozen=True)
class RobustnessRow:
    """One point of a curve: a target on a scene set under a factor of the disturbances at a level.

    :param label: the target's label
    :param factor: :data:`ALL_PARTS` or a part's name
    :param level: the level the factor's errors were scaled by
    :param scenes: the scene set
    :param result: its evaluation (level 0: the one ideal evaluation every factor shares)
    :param folder: where its evaluation files are
    :param seconds: the evaluation's wall time (s)
    """

    label: str
    factor: str
    level: float
    scenes: str
    result: EvaluationResult
    folder: Path
    seconds: float

    def cells(self) -> dict[str, Any]:
        """The row's figures (see the module docstring), as plain data: what ``robustness.json`` holds."""
        figures = BenchmarkRow(self.label, self.scenes, self.result, self.folder, self.seconds).cells()
        episodes = self.result.episodes
        touched = sum(episode["collisions_agent"] > 0 or episode["collisions_obstacle"] > 0 for episode in episodes)
        shapes = [episode["bearing_error"] for episode in episodes if episode["success"]]
        return {
            "target": self.label,
            "factor": self.factor,
            "level": self.level,
            **figures,
            "episodes_with_contacts": int(touched),
            "contact_rate": touched / len(episodes),
            "contact_rate_ci95": list(wilson_interval(int(touched), len(episodes))),
            "shape_error_ci95": mean_interval(shapes),
            "folder": Path(self.label, self.factor, level_name(self.level), self.scenes).as_posix(),
        }


def mean_interval(values: Sequence[float]) -> list[float] | None:
    """A 95 % interval of the mean of ``values`` (errors, >= 0): 1.96 standard errors (sample standard deviation)
    either side, the lower end at least 0; ``None`` for fewer than two values."""
    if len(values) < 2:
        return None
    mean, spread = float(np.mean(values)), float(np.std(values, ddof=1)) / math.sqrt(len(values))
    return [max(mean - Z95 * spread, 0.0), mean + Z95 * spread]  # the errors are >= 0


def check_levels(levels: Any) -> tuple[float, ...]:
    """The levels of a sweep, ascending, once they are valid: a list of at most :data:`MAX_LEVELS` distinct finite
    numbers in [0, :data:`MAX_LEVEL`].

    :raises ValueError: naming the first problem
    """
    if not isinstance(levels, (list, tuple)):
        raise ValueError(f"levels must be a list of numbers such as [0, 0.5, 1], got {levels!r:.60}")
    if not 1 <= len(levels) <= MAX_LEVELS:
        raise ValueError(f"give 1 to {MAX_LEVELS} levels, got {len(levels)}")
    for level in levels:
        if not (is_number(level) and 0 <= level <= MAX_LEVEL):
            raise ValueError(f"a level must be a finite number in [0, {MAX_LEVEL:g}], got {level!r:.60}")
    values = sorted(float(level) + 0.0 for level in levels)  # -0.0 is 0
    if len(set(values)) != len(values):
        raise ValueError(f"levels must differ, got {list(levels)}")
    return tuple(values)


def check_profile(disturbances: str | os.PathLike[str] | Disturbances) -> Disturbances:
    """The disturbances a sweep scales, once they can be scaled: some error, a level that the sweep sets (not drawn per
    episode).

    :raises ValueError: not a profile or a valid file, no error at all, or ``randomise`` on
    """
    world = load_disturbances(disturbances)
    name = "the disturbances given" if isinstance(disturbances, Disturbances) else f"disturbances {disturbances}"
    if world.is_ideal:
        raise ValueError(f"{name} have no error to scale: give a profile such as realistic or harsh, or a file")
    if world.randomise:
        raise ValueError(f"{name} draw their level per episode (randomise: true); a robustness curve sets it itself")
    return world


def robustness_factors(world: Disturbances, factors: bool | Sequence[str] = True) -> tuple[str, ...]:
    """The factors a sweep plays: :data:`ALL_PARTS` first, then the parts alone.

    :param world: the profile's disturbances
    :param factors: ``True``: every part the profile disturbs (none when it disturbs one only: that part is ``all``);
        ``False``: ``all`` only; a list of parts' names: those
    :raises ValueError: an unknown part, one named twice, or a part the profile does not disturb
    """
    if isinstance(factors, bool):
        disturbed = [part for part in PARTS if not getattr(world, part).is_ideal]
        return (ALL_PARTS, *(disturbed if factors and len(disturbed) > 1 else ()))
    if isinstance(factors, str) or not isinstance(factors, Sequence):
        raise ValueError(f"factors must be true, false or a list of parts {list(PARTS)}, got {factors!r:.60}")
    for part in factors:
        if part not in PARTS:
            raise ValueError(f"unknown factor {part!r}; factors are parts of the disturbances: {list(PARTS)}")
        if getattr(world, part).is_ideal:
            raise ValueError(f"factor {part!r}: the disturbances have no {part} errors to scale")
    if len(set(factors)) != len(factors):
        raise ValueError(f"factors must differ, got {list(factors)}")
    return (ALL_PARTS, *factors)


def level_name(level: float) -> str:
    """A level as a folder and table shows it: the shortest text that reads back as it (``1``, ``0.25``)."""
    text = repr(float(level))
    return text.removesuffix(".0")


def check_robustness_inputs(
    targets: Sequence[Target | str | os.PathLike[str]],
    labels: Sequence[str],
    out: str | os.PathLike[str],
    disturbances: str | os.PathLike[str] | Disturbances,
    levels: Any,
    factors: bool | Sequence[str],
    scenes: Sequence[str],
) -> tuple[list[Target], Disturbances, tuple[float, ...], tuple[str, ...]]:
    """Check a sweep's inputs before any work (:func:`run_robustness` calls it first; the command line too, before it
    loads the models).

    :return: the targets parsed, the profile, the levels ascending and the factors
    :raises ValueError: naming the first problem: labels not one distinct file name per target, unknown scene sets,
        an ``out`` that holds files, the profile (:func:`check_profile`), levels (:func:`check_levels`) or factors
        (:func:`robustness_factors`)
    """
    parsed = [Target.parse(target) for target in targets]
    if not parsed:
        raise ValueError("give at least one target")
    if isinstance(labels, str) or len(labels) != len(parsed) or len(set(labels)) != len(labels):
        raise ValueError(f"give one distinct label per target, got {list(labels)} for {len(parsed)} targets")
    for label in labels:
        check_name(label, "label")
        if label in (TABLE_FILE, RESULTS_FILE, FIGURES_FOLDER, LOCK_FILE):
            raise ValueError(f"label {label!r} is the name of a file the sweep writes beside the targets' folders")
    if isinstance(scenes, str) or not scenes or len(set(scenes)) != len(scenes):
        raise ValueError(f"scenes must be a list of distinct scene sets of {list(BENCHMARK_SCENES)}, got {scenes!r:.80}")
    unknown = [name for name in scenes if name not in BENCHMARK_SCENES]
    if unknown:
        raise ValueError(f"unknown scene set(s) {unknown}; the benchmark's: {list(BENCHMARK_SCENES)}")
    if holds_files(Path(out)):
        raise ValueError(f"{out} already holds files: give a new or empty folder (nothing was written)")
    world = check_profile(disturbances)
    return parsed, world, check_levels(levels), robustness_factors(world, factors)


def run_robustness(
    targets: Sequence[Target | str | os.PathLike[str]],
    labels: Sequence[str],
    out: str | os.PathLike[str],
    disturbances: str | os.PathLike[str] | Disturbances = "realistic",
    levels: Sequence[float] = ROBUSTNESS_LEVELS,
    factors: bool | Sequence[str] = True,
    episodes: int = BENCHMARK_EPISODES,
    seed: int = BENCHMARK_SEED,
    scenes: Sequence[str] = BENCHMARK_SCENES,
    n_envs: int = 16,
    workers: int = 1,
    recipe: str | None = None,
    device: str = "auto",
    progress_bar: bool = False,
    command: str = "",
) -> list[RobustnessRow]:
    """Play every target on every scene set under the disturbances scaled by each level (and, with factors, under each
    part alone); write each evaluation under ``out/<label>/<factor>/<level>/<scenes>/``, then the table
    (``robustness.md``) and its figures as data (``robustness.json``). Inputs are checked first
    (:func:`check_robustness_inputs`).

    :param targets: targets, or what :meth:`~sb3_formation.experiment.targets.Target.parse` reads (run folders, model
        files, ``<kind>:<name>`` targets)
    :param labels: one label per target (folder names)
    :param out: the sweep's folder: new or empty
    :param disturbances: the profile scaled: a name (``realistic``, ``harsh``), a file or
        :class:`~sb3_formation.env.disturbances.Disturbances`
    :param levels: the levels (0: ideal, 1: the profile), in [0, :data:`MAX_LEVEL`]
    :param factors: also sweep the parts alone (see :func:`robustness_factors`)
    :param episodes: episodes per point and scene set
    :param seed: episode k is played from ``reset(seed=seed + k)``
    :param scenes: the scene sets (default :data:`~sb3_formation.env.scenes.BENCHMARK_SCENES`)
    :param n_envs: teams played at once
    :param workers: processes stepping the teams, this one included
    :param recipe: the recipe of ``controller:`` targets
    :param device: torch device of learned targets
    :param progress_bar: show each evaluation's progress bar
    :param command: the command line that ran the sweep, recorded with the table
    :return: the rows, by target, scene set, factor and level
    """
    parsed, world, levels, chosen = check_robustness_inputs(targets, labels, out, disturbances, levels, factors, scenes)
    out = Path(out)
    protocol = EvaluationSection(
        episodes=episodes, stage=3, seed=seed, n_envs=min(n_envs, episodes), deterministic=True, record=1
    )
    rows = []
    for target, label in zip(parsed, labels):
        if target.kind == "controller":  # others act in their own task
            target = target.with_recipe(recipe)
        for scene_set in scenes:
            shared: tuple[EvaluationResult, float] | None = None  # level 0: one ideal evaluation for every factor
            for factor in chosen:
                errors = world if factor == ALL_PARTS else world.only(factor)
                for level in levels:
                    folder = out / label / factor / level_name(level) / scene_set
                    if level == 0 and shared is not None:
                        shared[0].save(folder)
                        rows.append(RobustnessRow(label, factor, level, scene_set, shared[0], folder, shared[1]))
                        continue
                    started = time.perf_counter()
                    result = evaluate_target(
                        target,
                        protocol,
                        workers=min(workers, n_envs, episodes),
                        env_overrides={"scenes": scene_set, "disturbances": errors.scaled(level)},
                        device=device,
                        progress_bar=progress_bar,
                        out=folder,
                    )
                    seconds = time.perf_counter() - started
                    if level == 0:
                        shared = (result, seconds)
                    rows.append(RobustnessRow(label, factor, level, scene_set, result, folder, seconds))
    run = {
        "machine": machine_line(),
        "version": __version__,
        "command": command,
        "protocol": f"{episodes} episodes per point and scene set from seed {seed}, stage 3, deterministic actions, "
        f"{min(n_envs, episodes)} teams at once, {min(workers, n_envs, episodes)} worker(s)",
        "profile": {
            "name": "given" if isinstance(disturbances, Disturbances) else disturbance_label(os.fspath(disturbances)),
            "disturbances": world.to_dict(),
        },
        "levels": list(levels),
        "factors": list(chosen),
    }
    atomic_write(out / TABLE_FILE, robustness_header(run) + "\n\n" + robustness_table(rows) + "\n")
    atomic_write(out / RESULTS_FILE, json.dumps({"run": run, "rows": [row.cells() for row in rows]}, indent=2) + "\n")
    return rows


def read_robustness(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``robustness.json`` of a sweep's folder (or the file itself): ``run`` and ``rows`` as
    :meth:`RobustnessRow.cells` wrote them.

    :raises FileNotFoundError: there is none
    :raises ValueError: the file is not a sweep's (naming it)
    """
    path = Path(folder)
    path = path / RESULTS_FILE if path.is_dir() else path
    data = read_json(path)
    if not (isinstance(data, dict) and isinstance(data.get("run"), dict) and isinstance(data.get("rows"), list)):
        raise ValueError(f"{path} is not the robustness.json of `sb3-formation robustness` (no run and rows)")
    return data


def robustness_header(run: dict[str, Any]) -> str:
    """The lines that open ``robustness.md``: where, when and how the curves were measured, and under what."""
    command = f"`{run['command']}`" if run["command"] else "run from Python"
    factors = run["factors"][1:]
    alone = f"; each alone: {', '.join(factors)}" if factors else ""
    return (
        f"sb3-formation {run['version']} robustness curves, {run['machine']}: {command}.  \n{run['protocol']}.  \n"
        f"Disturbances {run['profile']['name']} scaled by each level (0: ideal, 1: the profile): all parts{alone}; "
        "level 0 is one evaluation that every factor shares."
    )


def robustness_table(rows: Sequence[RobustnessRow]) -> str:
    """The Markdown table of a sweep: a line per target, scene set, factor and level."""
    headings = ["target", "scenes", "factor", "level", "episodes", "success (95 % CI)"]
    headings += ["episodes with contacts (95 % CI)", "shape error (95 % CI)"]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * (len(headings) - 3)) + "|"]
    for row in rows:
        cells = row.cells()
        line = [cells["target"], cells["scenes"], cells["factor"], level_name(cells["level"]), str(cells["episodes"])]
        line.append(_share_cell(cells["success_rate"], cells["success_rate_ci95"]))
        line.append(_share_cell(cells["contact_rate"], cells["contact_rate_ci95"]))
        line.append(_mean_cell(cells["shape_error"], cells["shape_error_ci95"]))
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines)


def _share_cell(rate: float, interval: Sequence[float]) -> str:
    """A share with its interval, as the benchmark's table writes success: ``95% (86% - 98%)``."""
    low, high = interval
    return f"{rate:.0%} ({low:.0%} - {high:.0%})"


def _mean_cell(mean: float | None, interval: Sequence[float] | None) -> str:
    """A mean with its interval if it has one (``0.031 (0.027 - 0.035)``), ``-`` for none."""
    if mean is None:
        return "-"
    return f"{mean:.3f}" if interval is None else f"{mean:.3f} ({interval[0]:.3f} - {interval[1]:.3f})"
