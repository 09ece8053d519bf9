"""Policy targets: one registry that turns what a user names into a :class:`~sb3_formation.controllers.base.TeamPolicy`.

- a run folder (its final model, else its latest checkpoint) or a model ``.zip`` (normaliser statistics beside it);
- ``controller:<name>``: a hand-written controller of :data:`~sb3_formation.controllers.CONTROLLERS`, acting in the
  task of the recipe given as ``recipe`` (default ``ch5-bearing``);
- ``pretrained:<name>``: a policy shipped with the package (:mod:`~sb3_formation.experiment.pretrained`), acting in
  the task it was trained for (a ``recipe`` of another task is refused);
- an exported ``.onnx`` file, or ``onnx:<path>``: run by :class:`~sb3_formation.runtime.OnnxPolicy` (no torch), in a
  run folder or shipped policy folder like the model it was exported from;
- ``safe:<target>``: any of these behind the safety filter (:class:`~sb3_formation.safety.policy.SafePolicy`, default
  gains); its evaluations go to the folder of ``<target>``'s with ``-safe`` added to its name.

``evaluate``, ``render``, ``plot`` and ``compare`` of the command line and :func:`load_policy` in Python resolve targets
here; a new kind of target is a new entry of :data:`TARGET_KINDS`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.scenes import DEFAULT_SCENES
from sb3_formation.experiment.pretrained import load_pretrained, pretrained_folder
from sb3_formation.experiment.recipes import DEFAULT_RECIPE, Recipe, load_recipe, load_settings
from sb3_formation.experiment.runs import load_trained
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.model_files import trust_pickle


@dataclass(frozen=True)
class TargetKind:
    """What a ``<kind>:<name>`` target is.

    :param load: (name, recipe, device) -> the policy
    :param recipe: (name, recipe) -> the recipe whose evaluation protocol and task the target is evaluated in
    """

    load: Callable[[str, str | None, str], TeamPolicy]
    recipe: Callable[[str, str | None], Recipe]


def _controller(name: str, recipe: str | None, device: str) -> TeamPolicy:
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; controllers: {', '.join(sorted(CONTROLLERS))}")
    return CONTROLLERS[name](load_recipe(recipe or DEFAULT_RECIPE).config())


def _pretrained_recipe(name: str, recipe: str | None) -> Recipe:
    return load_recipe(recipe) if recipe else load_settings(pretrained_folder(name)).recipe


#: Target kinds written ``<kind>:<name>``.
TARGET_KINDS: dict[str, TargetKind] = {
    "controller": TargetKind(_controller, lambda name, recipe: load_recipe(recipe or DEFAULT_RECIPE)),
    "pretrained": TargetKind(load_pretrained, _pretrained_recipe),
}


#: Prefix of a target that names an exported ONNX file (the path alone works too when it ends in ``.onnx``).
ONNX_PREFIX = "onnx:"
#: Prefix of a target whose actions pass through the safety filter.
SAFE_PREFIX = "safe:"


def unfiltered_target(target: str | os.PathLike[str]) -> tuple[str | os.PathLike[str], bool]:
    """A target without its ``safe:`` prefix, and whether it had one."""
    if str(target).startswith(SAFE_PREFIX):
        return str(target).removeprefix(SAFE_PREFIX), True
    return target, False


def target_kind(target: str | os.PathLike[str]) -> str | None:
    """The kind of a ``<kind>:<name>`` target (behind ``safe:`` or not), or ``None`` for a path (``onnx:<path>``
    included)."""
    kind, separator, _ = str(unfiltered_target(target)[0]).partition(":")
    return kind if separator and kind in TARGET_KINDS else None


def target_name(target: str | os.PathLike[str]) -> str:
    """The name of a ``<kind>:<name>`` target (``safe:controller:classical`` -> ``classical``)."""
    return str(unfiltered_target(target)[0]).partition(":")[2]


def target_path(target: str | os.PathLike[str]) -> Path:
    """The path a path target names (``onnx:<path>`` and ``safe:<path>`` -> ``<path>``)."""
    return Path(str(unfiltered_target(target)[0]).removeprefix(ONNX_PREFIX))


def is_onnx_target(target: str | os.PathLike[str]) -> bool:
    """Whether a target names an exported ONNX file (``onnx:<path>``, or a path ending in ``.onnx``)."""
    return str(unfiltered_target(target)[0]).startswith(ONNX_PREFIX) or target_path(target).suffix == ".onnx"


def load_policy(
    target: str | os.PathLike[str],
    recipe: str | None = None,
    device: str = "auto",
    trusted: bool | None = None,
) -> TeamPolicy:
    """The policy a target names.

    :param target: a run folder, a model ``.zip``, an exported ``.onnx`` (or ``onnx:<path>``), or ``<kind>:<name>``
        (e.g. ``controller:random``)
    :param recipe: for ``controller:`` targets, the recipe whose task the controller acts in (default ``ch5-bearing``);
        a trained model acts in the task it was trained in, so a run takes none and ``pretrained:`` refuses another
    :param device: torch device of a trained model
    :param trusted: unpickle what a model file needs (see :func:`~sb3_formation.experiment.runs.load_trained`;
        ``None``: unless inside :func:`~sb3_formation.sb3.model_files.trust_pickle`)
    """
    target, safe = unfiltered_target(target)
    if safe:
        return SafePolicy(load_policy(target, recipe, device, trusted=trusted))
    kind = target_kind(target)
    with trust_pickle(trusted):
        if kind is not None:
            return TARGET_KINDS[kind].load(target_name(target), recipe, device)
        if recipe is not None:
            raise ValueError(f"a recipe applies to controller targets only; {target} acts in the task it was trained in")
        if is_onnx_target(target):
            return OnnxPolicy(target_path(target))
        return load_trained(target_path(target), device=device)


def run_folder(target: str | os.PathLike[str]) -> Path | None:
    """The run folder a path target belongs to (the folder itself, a model file in it, or a checkpoint's), or ``None``."""
    if target_kind(target) is not None:
        return None
    path = target_path(target)
    for folder in [path, *path.parents][:4]:  # run/, run/final_model.zip, run/checkpoints/iteration_k/model.zip
        if (folder / "config.yaml").is_file():
            return folder
    return None


def default_protocol(target: str | os.PathLike[str], recipe: str | None = None) -> dict:
    """The evaluation protocol of a target's recipe (``episodes``, ``stage`` and what else its ``evaluation:`` gives):
    the run's, or a ``<kind>:<name>`` target's :attr:`TargetKind.recipe`; empty for a model file outside any run
    folder."""
    kind = target_kind(target)
    if kind is not None:
        return TARGET_KINDS[kind].recipe(target_name(target), recipe).evaluation.to_dict()
    folder = run_folder(target)
    if folder is None:
        return {}
    return load_settings(folder).recipe.evaluation.to_dict()


def evaluation_folder(target: str | os.PathLike[str], recipe: str | None = None, scenes: str = DEFAULT_SCENES) -> Path:
    """Where the evaluation files of a target go by default: ``eval/`` in its run folder (or beside a model file),
    ``eval_<stem>/`` beside an exported ``<stem>.onnx`` (not over its model's), and
    ``evaluations/<kind>-<name>_<recipe>/`` in the working folder for a ``<kind>:<name>`` target; an evaluation on
    other scenes than the default (``scenes``) adds ``-<scenes>`` to the folder's name."""
    suffix = ("" if scenes == DEFAULT_SCENES else f"-{scenes}") + ("-safe" if unfiltered_target(target)[1] else "")
    kind = target_kind(target)
    if kind is not None:
        name = target_name(target)
        return Path("evaluations") / f"{kind}-{name}_{TARGET_KINDS[kind].recipe(name, recipe).name}{suffix}"
    path = target_path(target)
    if is_onnx_target(target):
        return path.parent / f"eval_{path.stem}{suffix}"
    return (path if path.is_dir() else path.parent) / f"eval{suffix}"


def evaluation_file(
    target: str | os.PathLike[str], name: str, recipe: str | None = None, scenes: str = DEFAULT_SCENES
) -> Path:
    """The evaluation file ``name`` (e.g. ``summary.json``) of a target: the file itself, in an eval folder, in a run
    folder's ``eval/``, or in a ``<kind>:<name>`` target's :func:`evaluation_folder`.

    :raises FileNotFoundError: there is none (the message says how to make it)
    """
    folder = evaluation_folder(target, recipe, scenes) if target_kind(target) is not None else target_path(target)
    for candidate in (folder, folder / name, evaluation_folder(target, recipe, scenes) / name):
        if candidate.is_file() and candidate.name == name:
            return candidate
    option = "" if scenes == DEFAULT_SCENES else f" --scenes {scenes}"
    raise FileNotFoundError(f"no {name} in {target}: run `sb3-formation evaluate {target}{option}` first")
