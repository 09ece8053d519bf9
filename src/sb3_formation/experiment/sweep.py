"""Multi-seed sweeps of a recipe on Ray: one trial per seed, each an ordinary run folder.

``sweep("recipes/thesis-ch5-bearing.yaml")`` trains, then evaluates, one run per seed of the recipe file's ``run:
seeds`` as Ray tasks (Ray core, ``pip install 'sb3-formation[ray]'``), on this machine or, with ``address``, on a Ray
cluster whose nodes share the log folder. Trial k writes ``<logdir>/<file>/seed_<s>/``; a trial whose run folder already holds
its final model and evaluation is skipped, one with a checkpoint is resumed, so starting a sweep again finishes it.
A failing trial is reported with its error and does not stop the others. At the end the sweep writes
``aggregate.json`` and ``aggregate.md`` (mean and std over seeds) beside the run folders (``sb3-formation sweep`` also
draws ``training_curves.png`` there, with :func:`~sb3_formation.viz.plots.save_sweep_curves`).
"""

from __future__ import annotations

import json
import math
import os
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from sb3_formation.experiment.evaluation import SUMMARY_FILE, evaluate_target, load_summary
from sb3_formation.experiment.recipes import TrainSettings, load_settings
from sb3_formation.experiment.reports import TABLE_METRICS, table_number
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.training import resume, train
from sb3_formation.sb3.metrics import EPISODE_METRICS
from sb3_formation.utils.files import atomic_write


def run_trial(settings: dict[str, Any], run_dir: str) -> dict[str, Any]:
    """Train (or resume, or skip) one seed's run in ``run_dir`` and evaluate it; the body of a sweep's Ray task.

    :param settings: :meth:`TrainSettings.to_dict` of the trial
    :param run_dir: the trial's run folder
    :return: ``status`` ("skipped" or "trained"), ``run_dir`` and the evaluation ``summary``
    """
    folder = Path(run_dir)
    trial = TrainSettings.from_dict(settings)
    if (folder / FINAL_MODEL).exists() and (folder / "eval" / SUMMARY_FILE).exists():
        return {"status": "skipped", "run_dir": run_dir, "summary": load_summary(folder / "eval")}
    if not (folder / FINAL_MODEL).exists():
        if (folder / "config.yaml").exists():  # a trial that was stopped: from its checkpoint, or again from the start
            resume(folder)
        else:
            train(trial, command=f"sb3-formation sweep (trial {folder.name})", run_dir=folder)
    summary = evaluate_target(folder, trial.recipe.evaluation).summary
    return {"status": "trained", "run_dir": run_dir, "summary": summary}


@dataclass
class SweepResult:
    """What :func:`sweep` did.

    :param folder: the sweep's folder (run folders and aggregate files)
    :param label: the recipe file's name and the recipe's, e.g. for a figure's legend
    :param trials: per seed: ``status`` ("skipped", "trained" or "failed"), ``run_dir``, ``summary`` or ``error``
    """

    folder: Path
    label: str = ""
    trials: dict[int, dict[str, Any]] = field(default_factory=dict)

    @property
    def failed(self) -> dict[int, str]:
        """Seed -> error of the trials that failed."""
        return {seed: trial["error"] for seed, trial in self.trials.items() if trial["status"] == "failed"}

    @property
    def run_dirs(self) -> list[Path]:
        """The run folders of the trials that did not fail, by seed."""
        return [Path(trial["run_dir"]) for _, trial in sorted(self.trials.items()) if trial["status"] != "failed"]


def aggregate(summaries: list[dict[str, Any]], over: str = "successful") -> dict[str, dict[str, float | None]]:
    """Mean and std over seeds of the success rate and of each metric's per-seed mean (``None`` where no seed has one).

    :param summaries: evaluation summaries, one per seed
    :param over: per-seed means over ``"successful"`` (the thesis's choice) or ``"all"`` episodes
    """
    table: dict[str, dict[str, float | None]] = {}
    rates = np.array([summary["success_rate"] for summary in summaries])
    table["success_rate"] = {"mean": float(rates.mean()), "std": float(rates.std()), "seeds": len(rates)}
    for name in EPISODE_METRICS:
        means = [summary[f"{over}_episodes"][name]["mean"] for summary in summaries]
        values = np.array([value for value in means if value is not None], dtype=np.float64)
        table[name] = (
            {"mean": float(values.mean()), "std": float(values.std()), "seeds": len(values)}
            if len(values)
            else {"mean": None, "std": None, "seeds": 0}
        )
    return table


def aggregate_markdown(name: str, tables: dict[str, dict[str, dict[str, float | None]]]) -> str:
    """A Markdown table of :func:`aggregate`'s results, one row per kind of episode mean (``successful``, ``all``)."""
    headings = ["recipe", "means over", "seeds", "success rate", *(metric.label for metric in TABLE_METRICS.values())]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---", "---"] + ["---:"] * (len(headings) - 2)) + "|"]
    for over, table in tables.items():
        cells = [name, f"{over} episodes", str(table["success_rate"]["seeds"])]
        for metric in ("success_rate", *TABLE_METRICS):
            mean, std = table[metric]["mean"], table[metric]["std"]
            if mean is None:
                cells.append("-")
            else:
                sd = cast(float, std)  # a mean always comes with its std
                cells.append(
                    f"{mean:.1%} ± {sd:.1%}" if metric == "success_rate" else f"{table_number(mean)} ± {table_number(sd)}"
                )
        lines.append("| " + " | ".join(cells) + " |")
    return (
        "\n".join(lines) + "\n\nMean ± std over seeds of each seed's success rate and of its mean over the episodes named.\n"
    )


def sweep(
    recipe: str | os.PathLike[str],
    seeds: list[int] | None = None,
    address: str | None = None,
    max_concurrent: int | None = None,
    logdir: str | os.PathLike[str] | None = None,
    cpus_per_trial: float = 1.0,
) -> SweepResult:
    """Train and evaluate every seed of a recipe as Ray tasks, then aggregate over the seeds.

    :param recipe: a recipe file with its ``run:`` section (``recipes/<name>.yaml``), or a shipped recipe's name
    :param seeds: the seeds (default: the recipe file's ``run: seeds``, else its ``seed``)
    :param address: a Ray cluster's address (default: start Ray on this machine with its cores)
    :param max_concurrent: trials running at once (default: as many as the cluster's CPUs allow)
    :param logdir: folder of the sweep's folder ``<logdir>/<file>`` (default: the recipe file's ``run: logdir``)
    :param cpus_per_trial: CPUs Ray reserves for each trial
    """
    import ray

    settings = load_settings(recipe)
    seeds = list(seeds or settings.run.seeds or [settings.run.seed])
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must differ, got {seeds}")
    if max_concurrent is not None and max_concurrent < 1:
        raise ValueError(f"max_concurrent must be >= 1, got {max_concurrent}")
    name = Path(recipe).stem
    folder = Path(logdir or settings.run.logdir) / name
    folder.mkdir(parents=True, exist_ok=True)
    trials = {seed: (settings.replace_run(seed=seed, progress_bar=False), folder / f"seed_{seed}") for seed in seeds}
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    running: dict[Any, int] = {}
    try:
        task = ray.remote(num_cpus=cpus_per_trial, max_retries=0)(run_trial)
        limit = max_concurrent or max(1, math.floor(ray.cluster_resources().get("CPU", 1) / cpus_per_trial))
        result = SweepResult(folder, name if settings.recipe.name == name else f"{name} ({settings.recipe.name})")
        waiting = list(trials.items())
        while waiting or running:
            while waiting and len(running) < limit:
                seed, (trial, run_dir) = waiting.pop(0)
                running[task.remote(trial.to_dict(), str(run_dir))] = seed
                print(f"trial seed {seed}: started in {run_dir}")
            done, _ = ray.wait(list(running), num_returns=1, timeout=0.5)  # a timeout keeps Ctrl-C responsive
            if not done:
                continue
            seed = running.pop(done[0])
            try:
                result.trials[seed] = ray.get(done[0])
            except Exception as error:  # a failed trial is reported; the others go on
                message = _root_error(error)
                result.trials[seed] = {"status": "failed", "run_dir": str(trials[seed][1]), "error": message}
                print(f"trial seed {seed}: FAILED: {message}")
            else:
                print(f"trial seed {seed}: {result.trials[seed]['status']}")
    finally:
        for reference in running:  # interrupted: stop the trials under way (they resume when the sweep starts again)
            ray.cancel(reference, force=True)
        if started_here:
            ray.shutdown()
    _write_aggregate(result, name)
    return result


def _root_error(error: BaseException) -> str:
    """The original exception of a Ray task error, as one line."""
    cause = getattr(error, "cause", None) or error
    text = "".join(traceback.format_exception_only(type(cause), cause)).strip().splitlines()
    return text[-1] if text else repr(cause)


def _write_aggregate(result: SweepResult, name: str) -> None:
    """``aggregate.json`` and ``aggregate.md`` over the trials that have an evaluation."""
    done = {seed: trial for seed, trial in sorted(result.trials.items()) if trial["status"] != "failed"}
    if not done:
        return
    summaries = [trial["summary"] for trial in done.values()]
    tables = {over: aggregate(summaries, over) for over in ("successful", "all")}
    atomic_write(result.folder / "aggregate.json", json.dumps({"seeds": list(done), **tables}, indent=2))
    markdown = aggregate_markdown(name, tables)
    atomic_write(result.folder / "aggregate.md", markdown)
    print(markdown)
