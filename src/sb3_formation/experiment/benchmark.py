"""The benchmark: every target on the thesis's stage 3 and on every scene family, with fixed seeds, in one table.

Protocol (``sb3-formation benchmark``): each target plays ``episodes`` episodes (100 by default) of each scene set of
:data:`~sb3_formation.env.scenes.BENCHMARK_SCENES` (the scenes registry's entries but mixtures: the thesis's stage 3,
then every family) at stage 3, episode k from ``reset(seed=seed + k)`` (seed 10,000 by default: seeds that no
training run of the package draws, which start at 0 for the first team), with deterministic actions, in teams of the
target's own size unless ``n_agents`` is given. A row reports:

- success: the share of episodes whose centroid reached the goal, with its Wilson 95 % interval;
- shape error: the bearing error (the mean over agents and steps of norm(g_ref - g) over the two neighbours) averaged
  over the successful episodes. It is free of scale, so a formation that shrinks to pass keeps its score, and one
  that passes in single file or loses its shape shows it;
- agent and obstacle contacts per episode (over all episodes; a touching pair of agents counts once per step, an
  agent touching a shape or the border once per step), and of the obstacle contacts those where a moving obstacle
  ran into an agent that was braking, standing or moving away (``rammed``; every other contact is one the agent
  drove into); "-" in a still world;
- failed: the agents that failed per episode, under a task whose agents may fail ("-" otherwise); the success, shape
  error and contacts of such episodes are the flying agents';
- contact episodes: the episodes with agent contacts plus the episodes with obstacle contacts (an episode with both
  counts twice), so that 0 reads "no contact of any kind in any episode";
- steps per episode over the successful episodes;
- seconds: the evaluation's wall time;
- for a policy behind the safety filter (``safe:<target>``): the share of agent-steps whose action the filter changed
  and the mean size of a change (means over episodes), its infeasible agent-steps per episode, and the smallest
  separation (m) the agents measured in any episode; "-" for an unfiltered policy.

``benchmark.md`` opens with the run's provenance (date, CPU, cores, package version, command, protocol), then the
table; ``benchmark.json`` holds the same as data (``run`` and ``rows``).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sb3_formation import __version__
from sb3_formation.env.disturbances import disturbance_label, load_disturbances
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.evaluation import EvaluationResult, evaluate_target
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.files import atomic_write
from sb3_formation.utils.machine import machine_line

#: The first seed of the benchmark's episodes.
BENCHMARK_SEED = 10_000
#: Episodes per target and scene set.
BENCHMARK_EPISODES = 100
TABLE_FILE, RESULTS_FILE = "benchmark.md", "benchmark.json"


@dataclass(frozen=True)
class BenchmarkRow:
    """One target on one scene set.

    :param label: the target's label
    :param scenes: the scene set
    :param result: its evaluation
    :param folder: where its evaluation files are
    :param seconds: the evaluation's wall time (s)
    """

    label: str
    scenes: str
    result: EvaluationResult
    folder: Path
    seconds: float

    def cells(self) -> dict[str, Any]:
        """The row's figures (see the module docstring), as plain data."""
        summary = self.result.summary
        successful, everything = summary["successful_episodes"], summary["all_episodes"]
        return {
            "target": self.label,
            "scenes": self.scenes,
            "episodes": summary["episodes"],
            "n_agents": summary["n_agents"],
            "success_rate": summary["success_rate"],
            "success_rate_ci95": summary["success_rate_ci95"],
            "shape_error": successful["bearing_error"]["mean"],
            "agent_contacts": everything["collisions_agent"]["mean"],
            "obstacle_contacts": everything["collisions_obstacle"]["mean"],
            "rammed_contacts": everything.get("collisions_rammed", {}).get("mean"),
            "failed_agents": everything.get("failed_agents", {}).get("mean"),
            "contact_episodes": summary["episodes_with_contacts"]["agent"] + summary["episodes_with_contacts"]["obstacle"],
            "steps": successful["length"]["mean"],
            "seconds": self.seconds,
            "filter_changed": everything.get("filter_changed_fraction", {}).get("mean"),
            "filter_change": everything.get("filter_change_mean", {}).get("mean"),
            "infeasible_steps": everything.get("filter_infeasible_steps", {}).get("mean"),
            "min_separation": summary.get("min_separation"),
        }


def run_benchmark(
    targets: Sequence[Target | str | os.PathLike[str]],
    labels: Sequence[str],
    out: str | os.PathLike[str],
    episodes: int = BENCHMARK_EPISODES,
    seed: int = BENCHMARK_SEED,
    n_agents: int | None = None,
    n_envs: int = 16,
    workers: int = 1,
    recipe: str | None = None,
    device: str = "auto",
    progress_bar: bool = False,
    scenes: Sequence[str] = BENCHMARK_SCENES,
    command: str = "",
    disturbances: str = "ideal",
) -> list[BenchmarkRow]:
    """Evaluate every target on every scene set; write each evaluation under ``out/<label>/<scenes>/``, then the table
    (``benchmark.md``) and its figures as data (``benchmark.json``).

    :param targets: targets, or what :meth:`~sb3_formation.experiment.targets.Target.parse` reads (run folders, model
        files, ``<kind>:<name>`` targets)
    :param labels: one label per target (folder names)
    :param out: the benchmark's folder
    :param episodes: episodes per target and scene set
    :param seed: episode k is played from ``reset(seed=seed + k)``
    :param n_agents: team size (default: each target's own)
    :param n_envs: teams played at once
    :param workers: processes stepping the teams, this one included
    :param recipe: the recipe of ``controller:`` targets
    :param device: torch device of learned targets
    :param progress_bar: show each evaluation's progress bar
    :param scenes: the scene sets (default :data:`~sb3_formation.env.scenes.BENCHMARK_SCENES`)
    :param command: the command line that ran the benchmark, recorded with the table
    :param disturbances: what the episodes meet: a profile's name or a file
        (:func:`~sb3_formation.env.disturbances.load_disturbances`)
    """
    if len(labels) != len(targets) or len(set(labels)) != len(labels):
        raise ValueError(f"give one distinct label per target, got {list(labels)} for {len(targets)} targets")
    out = Path(out)
    world = load_disturbances(disturbances)
    protocol = EvaluationSection(
        episodes=episodes, stage=3, seed=seed, n_envs=min(n_envs, episodes), deterministic=True, record=1
    )
    rows = []
    for text, label in zip(targets, labels):
        target = Target.parse(text)
        if target.kind == "controller":  # others act in their own task
            target = target.with_recipe(recipe)
        for scene_set in scenes:
            overrides: dict[str, Any] = {"scenes": scene_set, "disturbances": world}
            if n_agents is not None:
                overrides["n_agents"] = n_agents
            folder = out / label / scene_set
            started = time.perf_counter()
            result = evaluate_target(
                target,
                protocol,
                workers=min(workers, n_envs, episodes),
                env_overrides=overrides,
                device=device,
                progress_bar=progress_bar,
                out=folder,
            )
            rows.append(BenchmarkRow(label, scene_set, result, folder, time.perf_counter() - started))
    run = {
        "machine": machine_line(),
        "version": __version__,
        "command": command,
        "protocol": f"{episodes} episodes per scene set from seed {seed}, stage 3, deterministic actions, "
        f"{min(n_envs, episodes)} teams at once, {min(workers, n_envs, episodes)} worker(s)"
        + ("" if world.is_ideal else f", disturbances {disturbance_label(disturbances)}"),
    }
    atomic_write(out / TABLE_FILE, benchmark_header(run) + "\n\n" + benchmark_table(rows) + "\n")
    atomic_write(out / RESULTS_FILE, json.dumps({"run": run, "rows": [row.cells() for row in rows]}, indent=2) + "\n")
    return rows


def benchmark_header(run: dict[str, str]) -> str:
    """The lines that open ``benchmark.md``: where, when and how the table was measured."""
    command = f"`{run['command']}`" if run["command"] else "run from Python"
    return f"sb3-formation {run['version']} benchmark, {run['machine']}: {command}.  \n{run['protocol']}."


def benchmark_table(rows: Sequence[BenchmarkRow]) -> str:
    """The Markdown table of a benchmark: a line per target and scene set."""
    headings = ["target", "scenes", "n", "episodes", "success (95 % CI)", "shape error", "agent contacts"]
    headings += ["obstacle contacts", "rammed", "failed", "contact episodes", "steps", "seconds", "filter changed"]
    headings += ["mean change"]
    headings += ["infeasible steps", "min separation (m)"]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * (len(headings) - 2)) + "|"]
    formats = {"shape_error": ".3f", "agent_contacts": ".2f", "obstacle_contacts": ".2f", "rammed_contacts": ".2f"}
    formats |= {"failed_agents": ".2f", "contact_episodes": "d"}
    formats |= {"steps": ".0f", "seconds": ".0f", "filter_changed": ".2%", "filter_change": ".3f"}
    formats |= {"infeasible_steps": ".2f", "min_separation": ".3f"}
    for row in rows:
        cells = row.cells()
        low, high = cells["success_rate_ci95"]
        line = [cells["target"], cells["scenes"], str(cells["n_agents"]), str(cells["episodes"])]
        line.append(f"{cells['success_rate']:.0%} ({low:.0%} - {high:.0%})")
        line += ["-" if cells[name] is None else format(cells[name], spec) for name, spec in formats.items()]
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines)
