"""What several subcommands share: help texts, the evaluation protocol's options, printing a summary."""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from sb3_formation.env.config import MAX_AGENTS, MAX_EPISODE_STEPS
from sb3_formation.env.disturbances import disturbance_label, load_disturbances
from sb3_formation.env.scenes import BENCHMARK_SCENES, SCENES
from sb3_formation.experiment.evaluation import EVALUATION_TEAMS, evaluate_target
from sb3_formation.experiment.recipes import DEFAULT_RECIPE, MAX_TEAMS
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.targets import Target
from sb3_formation.sb3.model_files import trust_pickle
from sb3_formation.utils.arguments import MAX_EPISODES, count, seed_value
from sb3_formation.utils.checks import check_name
from sb3_formation.utils.yaml_files import read_yaml

# Command-line value types ---------------------------------------------------------------------------------------------
# Every count option is bounded by a documented maximum (count): a larger one would overflow a C integer or allocate
# without bound. Every path a command writes to is checked as it is read (output_path): before any work.

#: ``--episodes`` at most :data:`~sb3_formation.utils.arguments.MAX_EPISODES`.
episodes_count = count(MAX_EPISODES)
#: ``--n-envs``, ``--workers`` (a worker steps whole teams) at most :data:`~sb3_formation.experiment.recipes.MAX_TEAMS`.
teams_count = count(MAX_TEAMS)
#: ``--agents`` at most :data:`~sb3_formation.env.config.MAX_AGENTS` (the task's own check names a team below 3).
agents_count = count(MAX_AGENTS)
#: ``--max-steps`` and counts of steps at most :data:`~sb3_formation.env.config.MAX_EPISODE_STEPS`.
steps_count = count(MAX_EPISODE_STEPS)
#: ``--fps`` of a video at most this many frames per second.
MAX_FPS = 1000
fps_count = count(MAX_FPS)


def assignment(text: str) -> tuple[str, object]:
    """``FIELD=VALUE``, the value read as YAML."""
    name, separator, value = text.partition("=")
    if not separator or not name:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    try:
        return name.strip(), read_yaml(value, f"the value of {name.strip()}")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def indices(text: str) -> list[int]:
    """Comma-separated integers >= 0 (episode indices, seeds)."""
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected episode indices such as 0,2,5, got {text!r}")
    return values


TARGET_HELP = (
    "a run folder, a model .zip (normaliser beside it), controller:<name> (e.g. controller:classical), "
    "pretrained:<name> (a shipped policy: sb3-formation pretrained) or an exported .onnx (onnx:<path>)"
)
RECIPE_HELP = (
    f"recipe of a controller: target (default {DEFAULT_RECIPE}); trained models act in the task they were trained in "
    "(pretrained: refuses another)"
)


def add_scenes_option(parser: argparse.ArgumentParser) -> None:
    """``--scenes NAME``: where episodes are placed (``FormationConfig.scenes``; default: the policy's or recipe's)."""
    parser.add_argument(
        "--scenes",
        choices=SCENES,
        help="where episodes are placed: curriculum (the thesis's) or a scene family (default: the policy's own)",
    )


DISTURBANCES_HELP = (
    "the errors of real robots the episodes meet: a profile (ideal, realistic, harsh, failures) or a YAML file of the "
    "same format (docs/disturbances.md; default ideal)"
)


def add_disturbances_option(parser: argparse.ArgumentParser) -> None:
    """``--disturbances NAME|FILE``: the disturbances the episodes meet (checked before any work)."""
    parser.add_argument("--disturbances", type=disturbances_source, help=DISTURBANCES_HELP)


def disturbances_source(text: str) -> str:
    """``--disturbances``' value, once it reads as disturbances (a profile's name or a valid file)."""
    try:
        load_disturbances(text)
    except (ValueError, FileNotFoundError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def disturbances_label(args: argparse.Namespace) -> str:
    """The label of ``--disturbances`` (``ideal`` when not given), for folders."""
    source = getattr(args, "disturbances", None)
    return "ideal" if source is None else disturbance_label(source)


def add_recipe_option(parser: argparse.ArgumentParser, help: str = RECIPE_HELP, **options: Any) -> None:
    """``--recipe NAME``: a shipped recipe's name or a recipe file."""
    parser.add_argument("--recipe", help=help, **options)


TRUST_PICKLE_HELP = (
    "also load model files that need unpickling (SB3's own load, which runs code the file holds): only files you "
    "trust; by default only plain data and tensors are read and such a file is refused"
)


def add_trust_pickle_option(parser: argparse.ArgumentParser, help: str = TRUST_PICKLE_HELP) -> None:
    """``--trust-pickle``, for subcommands that load model files (:func:`model_trust` applies it)."""
    parser.add_argument("--trust-pickle", action="store_true", help=help)


def model_trust(args: argparse.Namespace) -> AbstractContextManager[None]:
    """Within it, model files load as ``--trust-pickle`` says (:func:`~sb3_formation.sb3.model_files.trust_pickle`)."""
    return trust_pickle(args.trust_pickle)


def add_protocol_arguments(parser: argparse.ArgumentParser) -> None:
    """The evaluation protocol's options, shared by ``evaluate`` and ``compare``."""
    parser.add_argument(
        "--episodes",
        type=episodes_count,
        help=f"episodes, at most {MAX_EPISODES:,} (default: the recipe's; thesis: 500 ch. 4, 200 ch. 5)",
    )
    parser.add_argument("--stage", type=int, choices=(1, 2, 3), help="curriculum stage (default: the recipe's, 3)")
    parser.add_argument("--seed", type=seed_value, default=0, help="episode k plays the scenario of seed + k (default 0)")
    parser.add_argument(
        "--n-envs", type=teams_count, default=EVALUATION_TEAMS, help=f"teams played at once (default {EVALUATION_TEAMS})"
    )
    parser.add_argument(
        "--workers", type=teams_count, default=1, help="processes stepping the teams, this one included (default 1)"
    )
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_scenes_option(parser)
    add_disturbances_option(parser)
    add_recipe_option(parser)
    add_trust_pickle_option(parser)


def print_summary(summary: dict) -> None:
    """An evaluation summary: the success rate with its interval, then each metric's mean and std."""
    low, high = summary["success_rate_ci95"]
    print(
        f"{summary['episodes']} episodes (stage {summary['stage']}, seed {summary['seed']}): success rate "
        f"{summary['success_rate']:.1%} (95% CI {low:.1%} - {high:.1%})"
    )
    successful, everything = summary["successful_episodes"], summary["all_episodes"]
    print(f"  {'mean ± std over':<26}{'successful episodes':>24}{'all episodes':>24}")
    for name, statistics in everything.items():
        mine = successful.get(name, {"mean": None})  # (summaries written before 0.2 may lack a metric there)
        cell = "-" if mine["mean"] is None else f"{mine['mean']:.3f} ± {mine['std']:.3f}"
        print(f"  {name:<26}{cell:>24}{statistics['mean']:>15.3f} ± {statistics['std']:.3f}")


def protocol_changes(args: argparse.Namespace) -> dict[str, Any]:
    """The fields of the evaluation protocol (:class:`~sb3_formation.experiment.sections.EvaluationSection`) that the
    protocol options of ``args`` set (``None``: the recipe's)."""
    return {
        "episodes": args.episodes,
        "stage": args.stage,
        "seed": args.seed,
        "n_envs": args.n_envs,
        "deterministic": not args.stochastic,
        "record": getattr(args, "trajectories", 5),
    }


def evaluate_with_protocol(
    args: argparse.Namespace, target: Target, protocol: EvaluationSection | None = None, out: Path | None = None
) -> dict:
    """Evaluate one target, save its files, and return its summary.

    :param args: the protocol options (:func:`add_protocol_arguments`), ``--agents`` and ``--scenes``
    :param target: the target
    :param protocol: the protocol (default: the target's recipe's with the protocol options of ``args`` over it)
    :param out: folder for the files (default: the target's evaluation folder)
    """
    result = evaluate_target(
        target,
        protocol,
        changes=protocol_changes(args) if protocol is None else None,
        workers=min(args.workers, args.n_envs),
        env_overrides=scene_overrides(args),
        device=args.device,
        progress_bar=not args.no_progress,
        out=out,
        disturbances=args.disturbances,
    )
    print(f"{target}: evaluation written to {out or target.evaluation_folder(result.scenes, disturbances_label(args))}")
    return result.summary


def scene_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`FormationConfig` fields that ``--agents`` and ``--scenes`` change (those given)."""
    overrides = {"n_agents": getattr(args, "agents", None), "scenes": getattr(args, "scenes", None)}
    return {name: value for name, value in overrides.items() if value is not None}


def label_folders(labels: Sequence[str]) -> list[str]:
    """The folder name of each label (runs of other characters than letters, digits, ``_.-`` become ``-``).

    :raises ValueError: a name that is no folder name, or two labels that give one folder
    """
    folders = [re.sub(r"[^A-Za-z0-9_.-]+", "-", label) for label in labels]
    for folder in folders:
        check_name(folder, "label")
    if len(set(folders)) != len(folders):
        raise ValueError(f"labels must differ, got {list(labels)}")
    return folders


def target_labels(text: str | None, targets: Sequence[Target]) -> list[str]:
    """One label per target: from ``--labels`` (comma-separated), else each target's own
    (:attr:`~sb3_formation.experiment.targets.Target.label`)."""
    if text is None:
        return [target.label for target in targets]
    try:  # they are written into tables, figures and folder names: check before any work
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"--labels {text!r} is not valid UTF-8: give labels of UTF-8 characters") from None
    labels = [label.strip() for label in text.split(",")]
    if len(labels) != len(targets):
        raise ValueError(f"--labels gives {len(labels)} labels for {len(targets)} runs")
    return labels


def scene_sets(text: str) -> tuple[str, ...]:
    """``--scenes`` of the benchmark and the robustness curves: comma-separated scene sets of the benchmark, each once."""
    names = tuple(name.strip() for name in text.split(","))
    unknown = [name for name in names if name not in BENCHMARK_SCENES]
    if unknown or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"expected distinct scene sets of {', '.join(BENCHMARK_SCENES)} separated by commas, got {text!r:.60}"
        )
    return names


def add_scene_sets_option(parser: argparse.ArgumentParser) -> None:
    """``--scenes``: the benchmark's scene sets to play (default all of them)."""
    parser.add_argument(
        "--scenes",
        type=scene_sets,
        default=",".join(BENCHMARK_SCENES),
        help="comma-separated scene sets of the benchmark (default all of them)",
    )
