"""Policy targets: what a user names, parsed once (:meth:`Target.parse`) into a :class:`Target` that loads its
:class:`~sb3_formation.controllers.base.TeamPolicy`, names the recipe it is evaluated in and its evaluation folder.

- a run folder (its final model, else its latest checkpoint) or a model ``.zip`` (normaliser statistics beside it);
- ``controller:<name>``: a hand-written controller of :data:`~sb3_formation.controllers.CONTROLLERS`, acting in the
  task of the recipe given as ``recipe`` (default ``ch5-bearing``);
- ``pretrained:<name>``: a policy shipped with the package (:mod:`~sb3_formation.experiment.pretrained`), acting in
  the task it was trained for (a ``recipe`` of another task is refused);
- an exported ``.onnx`` file, or ``onnx:<path>``: run by :class:`~sb3_formation.runtime.OnnxPolicy` (no torch; behind
  the safety filter when it was trained behind one, :func:`~sb3_formation.runtime.load_onnx_policy`), in a run folder
  or shipped policy folder like the model it was exported from;
- ``safe:<target>``: any of these behind the safety filter (:class:`~sb3_formation.safety.policy.SafePolicy`, default
  gains); its evaluations go to the folder of ``<target>``'s with ``-safe`` added to its name (``safe:safe:<target>``
  is ``safe:<target>``: one filter).

``evaluate``, ``render``, ``plot``, ``compare``, ``benchmark`` and ``ros`` of the command line, and
:func:`load_policy` and :func:`~sb3_formation.experiment.evaluation.evaluate_target` in Python, parse what they are
given here; a new kind of target is a new entry of :data:`TARGET_KINDS`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.scenes import DEFAULT_SCENES
from sb3_formation.experiment.pretrained import load_pretrained, pretrained_folder
from sb3_formation.experiment.recipes import DEFAULT_RECIPE, Recipe, load_recipe, load_settings
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.runtime import load_onnx_policy
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.model_files import trust_pickle

#: Prefix of a target whose actions pass through the safety filter.
SAFE_PREFIX = "safe:"


@dataclass(frozen=True)
class TargetKind:
    """One kind of target: how it is written, how it loads, in which recipe and where it is evaluated.

    :param load: (target, device) -> the policy (unfiltered: ``safe:`` is the target's, not its kind's)
    :param recipe: target -> the recipe whose task and evaluation protocol the target is evaluated in, or ``None``
    :param folder: (target, suffix) -> the target's default evaluation folder, ``suffix`` added to its name
    :param prefixed: written ``<kind>:<name>``
    :param path: its name is a file or folder, evaluated beside it, acting in the task it was trained in (so it takes
        no recipe)
    :param suffix: a path ending in this (e.g. ``.onnx``) is of this kind without the prefix
    """

    load: Callable[[Target, str], TeamPolicy]
    recipe: Callable[[Target], Recipe | None]
    folder: Callable[[Target, str], Path]
    prefixed: bool = True
    path: bool = False
    suffix: str | None = None


def _load_controller(target: Target, device: str) -> TeamPolicy:
    if target.name not in CONTROLLERS:
        raise ValueError(f"unknown controller {target.name!r}; controllers: {', '.join(sorted(CONTROLLERS))}")
    return CONTROLLERS[target.name](_controller_recipe(target).config())


def _controller_recipe(target: Target) -> Recipe:
    return load_recipe(target.recipe or DEFAULT_RECIPE)


def _pretrained_recipe(target: Target) -> Recipe:
    return load_recipe(target.recipe) if target.recipe else load_settings(pretrained_folder(target.name)).recipe


def _run_recipe(target: Target) -> Recipe | None:
    folder = target.run_folder
    return None if folder is None else load_settings(folder).recipe


def _named_folder(target: Target, suffix: str) -> Path:
    """``evaluations/<kind>-<name>_<recipe>`` in the working folder."""
    recipe = cast(Recipe, target.task_recipe())  # a <kind>:<name> target's is never None
    return Path("evaluations") / f"{target.kind}-{target.name}_{recipe.name}{suffix}"


def _beside_model(target: Target, suffix: str) -> Path:
    """``eval/`` in a run folder, or beside a model file."""
    path = target.path
    return (path if path.is_dir() else path.parent) / f"eval{suffix}"


def _beside_export(target: Target, suffix: str) -> Path:
    """``eval_<stem>/`` beside an exported ``<stem>.onnx`` (not over its model's ``eval/``)."""
    return target.path.parent / f"eval_{target.path.stem}{suffix}"


#: The kinds of target by name: ``<name>:<...>`` for a prefixed kind; the first entry, unprefixed, is what a path
#: of no other kind is.
TARGET_KINDS: dict[str, TargetKind] = {
    "model": TargetKind(
        lambda target, device: load_trained(target.path, device=device),
        _run_recipe,
        _beside_model,
        prefixed=False,
        path=True,
    ),
    "onnx": TargetKind(
        lambda target, device: load_onnx_policy(target.path), _run_recipe, _beside_export, path=True, suffix=".onnx"
    ),
    "controller": TargetKind(_load_controller, _controller_recipe, _named_folder),
    "pretrained": TargetKind(
        lambda target, device: load_pretrained(target.name, target.recipe, device), _pretrained_recipe, _named_folder
    ),
}
#: The kind of a path that no prefix or suffix names.
DEFAULT_KIND = next(iter(TARGET_KINDS))


def find_run_folder(path: Path) -> Path | None:
    """The run folder ``path`` belongs to (the folder itself, a model file in it, or a checkpoint's), or ``None``."""
    for folder in [path, *path.parents][:4]:  # run/, run/final_model.zip, run/checkpoints/iteration_k/model.zip
        if (folder / "config.yaml").is_file():
            return folder
    return None


@dataclass(frozen=True)
class Target:
    """A policy target, parsed (:meth:`parse`): what it is, how it loads and where its evaluations go.

    :param kind: a name of :data:`TARGET_KINDS`
    :param name: the controller's or shipped policy's name, or the path (as written, without its prefix)
    :param safe: its actions pass through the safety filter (``safe:``)
    :param recipe: the recipe named for it (a shipped recipe's name or a recipe file): the task a controller acts in,
        the task a shipped policy must have been trained for; a path target acts in its own and refuses one when loaded
    :param text: the target as written, for messages (default: as :meth:`parse` reads it)
    """

    kind: str
    name: str
    safe: bool = False
    recipe: str | None = None
    text: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.kind not in TARGET_KINDS:
            raise ValueError(f"unknown kind of target {self.kind!r}; kinds: {', '.join(TARGET_KINDS)}")
        if not self.text:
            written = self.name if self.kind == DEFAULT_KIND else f"{self.kind}:{self.name}"
            object.__setattr__(self, "text", SAFE_PREFIX * self.safe + written)

    @classmethod
    def parse(cls, target: Target | str | os.PathLike[str], recipe: str | None = None) -> Target:
        """The target that ``target`` names (a :class:`Target` is returned as it is, with ``recipe`` if one is given).

        :param target: a run folder, a model ``.zip``, an exported ``.onnx`` (or ``onnx:<path>``), ``<kind>:<name>``
            (e.g. ``controller:random``), any of them behind ``safe:``
        :param recipe: the recipe named for it (see :attr:`recipe`)
        """
        if isinstance(target, Target):
            return target if recipe is None else dataclasses.replace(target, recipe=recipe)
        text = rest = os.fspath(target)
        safe = rest.startswith(SAFE_PREFIX)
        while rest.startswith(SAFE_PREFIX):  # safe:safe:X is safe:X: one filter
            rest = rest.removeprefix(SAFE_PREFIX)
        prefix, separator, name = rest.partition(":")
        if separator and prefix in TARGET_KINDS and TARGET_KINDS[prefix].prefixed:
            return cls(prefix, name, safe, recipe, text)
        suffix = Path(rest).suffix
        kind = next((key for key, kind in TARGET_KINDS.items() if suffix and kind.suffix == suffix), DEFAULT_KIND)
        return cls(kind, rest, safe, recipe, text)

    def __str__(self) -> str:
        return self.text

    @property
    def is_path(self) -> bool:
        """Whether the target names a file or folder (a run, a model file, an export) rather than ``<kind>:<name>``."""
        return TARGET_KINDS[self.kind].path

    @property
    def path(self) -> Path:
        """The file or folder a path target names.

        :raises ValueError: a ``<kind>:<name>`` target
        """
        if not self.is_path:
            raise ValueError(f"{self} names no file: it is a {self.kind} target")
        return Path(self.name)

    def with_recipe(self, recipe: str | None) -> Target:
        """The target with ``recipe`` as its recipe if it takes one (a ``<kind>:<name>`` target); a path target as it
        is (it acts in the task it was trained in)."""
        return self if self.is_path else dataclasses.replace(self, recipe=recipe)

    def load(self, device: str = "auto", trusted: bool | None = None) -> TeamPolicy:
        """The policy the target names.

        :param device: torch device of a trained model
        :param trusted: unpickle what a model file needs (see :func:`~sb3_formation.experiment.runs.load_trained`;
            ``None``: unless inside :func:`~sb3_formation.sb3.model_files.trust_pickle`)
        :raises ValueError: a recipe given for a path target (it acts in the task it was trained in)
        """
        if self.recipe is not None and self.is_path:
            raise ValueError(f"a recipe applies to controller targets only; {self} acts in the task it was trained in")
        with trust_pickle(trusted):
            policy = TARGET_KINDS[self.kind].load(self, device)
        return SafePolicy(policy) if self.safe else policy

    def task_recipe(self) -> Recipe | None:
        """The recipe whose task and evaluation protocol the target is evaluated in: a run's own (``None`` for a model
        file outside any run folder), a controller's :attr:`recipe` (default ``ch5-bearing``), a shipped policy's
        own unless :attr:`recipe` names one."""
        return TARGET_KINDS[self.kind].recipe(self)

    def protocol(self, **changes: Any) -> EvaluationSection:
        """The evaluation protocol of :meth:`task_recipe` with ``changes`` (fields of
        :class:`~sb3_formation.experiment.sections.EvaluationSection`; ``None`` keeps the recipe's) applied, as the
        section validates them.

        :raises ValueError: no recipe gives the number of episodes and ``changes`` give none, or an invalid value
        """
        changes = {name: value for name, value in changes.items() if value is not None}
        recipe = self.task_recipe()
        if recipe is not None:
            return recipe.evaluation.replace(**changes)
        if "episodes" not in changes:
            raise ValueError(f"{self} belongs to no run folder whose recipe gives the number of episodes: give --episodes")
        return EvaluationSection(**changes)

    @property
    def run_folder(self) -> Path | None:
        """The run folder a path target belongs to (the folder itself, a model file in it, or a checkpoint's), or
        ``None``."""
        return find_run_folder(self.path) if self.is_path else None

    def evaluation_folder(self, scenes: str = DEFAULT_SCENES, disturbances: str = "ideal") -> Path:
        """Where the evaluation files of the target go by default: ``eval/`` in its run folder (or beside a model file),
        ``eval_<stem>/`` beside an exported ``<stem>.onnx``, and ``evaluations/<kind>-<name>_<recipe>/`` in the working
        folder for a ``<kind>:<name>`` target; an evaluation on other scenes than the default (``scenes``) adds
        ``-<scenes>`` to the folder's name, one under disturbances (their label,
        :func:`~sb3_formation.env.disturbances.disturbance_label`) ``-<label>``, one behind the safety filter ``-safe``."""
        suffix = ("" if scenes == DEFAULT_SCENES else f"-{scenes}") + ("" if disturbances == "ideal" else f"-{disturbances}")
        return TARGET_KINDS[self.kind].folder(self, suffix + ("-safe" if self.safe else ""))

    def evaluation_file(self, name: str, scenes: str = DEFAULT_SCENES, disturbances: str = "ideal") -> Path:
        """The evaluation file ``name`` (e.g. ``summary.json``) of the target: the file itself, in an eval folder, in a
        run folder's ``eval/``, or in a ``<kind>:<name>`` target's :meth:`evaluation_folder`.

        :raises FileNotFoundError: there is none (the message says how to make it)
        """
        default = self.evaluation_folder(scenes, disturbances)
        folder = self.path if self.is_path else default
        for candidate in (folder, folder / name, default / name):
            if candidate.is_file() and candidate.name == name:
                return candidate
        option = ("" if scenes == DEFAULT_SCENES else f" --scenes {scenes}") + (
            "" if disturbances == "ideal" else f" --disturbances {disturbances}"
        )
        raise FileNotFoundError(f"no {name} in {self}: run `sb3-formation evaluate {self}{option}` first")

    @property
    def label(self) -> str:
        """The target's default label: ``<kind>:<name>`` (``safe:`` included), else a folder's name, the name of the
        folder holding a run's model file (``run/checkpoints/iteration_10/model.zip`` -> ``iteration_10``), or the
        name of a model file of no run (``policy.onnx`` -> ``policy``), ``safe-`` before it behind the filter."""
        if not self.is_path:
            return SAFE_PREFIX * self.safe + f"{self.kind}:{self.name}"
        path = self.path.resolve()
        if path.is_file() and find_run_folder(path) is None:  # a model file of no run: its own name
            label = path.stem
        else:
            label = (path if path.is_dir() else path.parent).name  # a run folder, or the folder of a run's model file
        return f"safe-{label}" if self.safe else label


def load_policy(
    target: Target | str | os.PathLike[str],
    recipe: str | None = None,
    device: str = "auto",
    trusted: bool | None = None,
) -> TeamPolicy:
    """The policy a target names (:meth:`Target.load` of :meth:`Target.parse`).

    :param target: a run folder, a model ``.zip``, an exported ``.onnx`` (or ``onnx:<path>``), or ``<kind>:<name>``
        (e.g. ``controller:random``)
    :param recipe: for ``controller:`` targets, the recipe whose task the controller acts in (default ``ch5-bearing``);
        a trained model acts in the task it was trained in, so a run takes none and ``pretrained:`` refuses another
    :param device: torch device of a trained model
    :param trusted: unpickle what a model file needs (see :func:`~sb3_formation.experiment.runs.load_trained`;
        ``None``: unless inside :func:`~sb3_formation.sb3.model_files.trust_pickle`)
    """
    return Target.parse(target, recipe).load(device, trusted)
