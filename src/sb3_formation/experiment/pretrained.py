"""Trained policies shipped with the package: ``pretrained:<name>`` targets and :func:`load_pretrained`.

A shipped policy is a trimmed run folder in ``sb3_formation/pretrained/<name>/``:

- ``final_model.zip``: the trained model without its optimiser state and last rollout (what acting does not need);
- ``final_normalizer.npz``: the observation normaliser's frozen statistics;
- ``final_model.onnx``: the same policy exported to ONNX (:func:`~sb3_formation.sb3.onnx_export.export_onnx`), for
  :class:`~sb3_formation.runtime.OnnxPolicy` without torch (``docs/export.md``);
- ``config.yaml``: the run's resolved settings (recipe, task configuration, PPO settings);
- ``eval/summary.json`` and ``eval/episodes.csv``: the evaluation of this very model file on its recipe's protocol
  (the thesis's: stage 3, fixed seeds from 0; 500 episodes in chapter 4, 200 in chapter 5);
- ``card.json``: how it was made (the training command, seed, wall time, agent-steps, package and library versions).

:func:`~sb3_formation.experiment.export.export_pretrained` makes one from a finished run
(``sb3-formation pretrained --export RUN --name NAME``).
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.experiment.recipes import load_recipe
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.statistics import check_summary
from sb3_formation.utils.checks import is_count, is_number
from sb3_formation.utils.files import read_json

#: Where the shipped policies live (package data).
PRETRAINED_DIR = Path(__file__).resolve().parent.parent / "pretrained"
CARD_FILE, SUMMARY_PATH, ONNX_FILE = "card.json", "eval/summary.json", "final_model.onnx"
#: Task fields a shipped policy may be evaluated with other values of (the curriculum stage is the protocol's).
FREE_FIELDS = frozenset({"stage"})


def pretrained_names(root: Path = PRETRAINED_DIR) -> list[str]:
    """The names of the shipped policies, sorted."""
    return sorted(path.parent.name for path in root.glob(f"*/{CARD_FILE}"))


def pretrained_folder(name: str, root: Path = PRETRAINED_DIR) -> Path:
    """The folder of the shipped policy ``name``.

    :raises ValueError: there is none of that name (the message lists the names)
    """
    folder = root / name
    if not name or "/" in name or not (folder / CARD_FILE).is_file():
        raise ValueError(f"no shipped policy {name!r}; shipped: {', '.join(pretrained_names(root)) or 'none'}")
    return folder


#: What every card records, and of what kind (the listing and ``--recipe`` read them).
CARD_KEYS: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "recipe": ("a recipe name", lambda value: isinstance(value, str)),
    "n_agents": ("an integer >= 1", lambda value: is_count(value) and value >= 1),
    "training_seconds": ("a number of seconds >= 0", lambda value: is_number(value) and value >= 0),
}


def pretrained_card(name: str, root: Path = PRETRAINED_DIR) -> dict[str, Any]:
    """What :func:`export_pretrained` recorded of a shipped policy, with its stored evaluation ``summary``.

    :raises ValueError: an unknown name, or a ``card.json`` or ``eval/summary.json`` that is damaged (naming the file
        and the entry)
    """
    folder = pretrained_folder(name, root)
    path = folder / CARD_FILE
    card = read_json(path)
    if not isinstance(card, dict):
        raise ValueError(f"{path} is damaged: it must hold a JSON object, got {type(card).__name__}")
    for key, (expected, valid) in CARD_KEYS.items():
        if key not in card:
            raise ValueError(f"{path} is damaged: it records no {key!r} ({expected}); export the policy again")
        if not valid(card[key]):
            raise ValueError(f"{path} is damaged: {key!r} must be {expected}, got {card[key]!r:.60}")
    sizes = card.get("team_sizes", [card["n_agents"]])
    if not (isinstance(sizes, list) and sizes and all(is_count(size) and size >= 1 for size in sizes)):
        raise ValueError(f"{path} is damaged: 'team_sizes' must be a list of integers >= 1, got {sizes!r:.60}")
    summary = read_json(folder / SUMMARY_PATH)
    check_summary(summary, folder / SUMMARY_PATH)
    card["summary"] = summary
    return card


def numerics_fingerprint() -> str:
    """SHA-256 of a fixed computation in the floating-point kernels an evaluation runs through (numpy's
    transcendental functions and products, torch's linear layers and tanh, at the batch sizes of an evaluation),
    independent of this package's code. CPUs with other vector units (AVX2, AVX-512, AMX) may round these differently
    in the last bit, which over thousands of steps changes episodes; where the fingerprint is the exporting machine's
    (``card.json``), a shipped policy's stored episodes must replay exactly.
    """
    digest = hashlib.sha256()
    inputs = np.random.default_rng(0).standard_normal((64, 215))
    for values in (np.sin(inputs), np.cos(inputs), np.arctan2(inputs, inputs[::-1]), np.exp(-inputs * inputs)):
        digest.update(values.tobytes())
    digest.update((inputs @ inputs.T).tobytes() + np.hypot(inputs, 1.0).tobytes() + np.linalg.norm(inputs, axis=1).tobytes())
    generator = torch.Generator().manual_seed(0)
    sizes = (215, 256, 256, 2)
    layers = [
        (torch.randn(out, into, generator=generator) / into**0.5, torch.randn(out, generator=generator))
        for into, out in itertools.pairwise(sizes)
    ]
    with torch.no_grad():
        for rows in (1, 48, 64):
            hidden = torch.as_tensor(inputs[:rows], dtype=torch.float32)
            for weight, bias in layers:
                hidden = torch.tanh(torch.nn.functional.linear(hidden, weight, bias))
            digest.update(hidden.numpy().tobytes())
    return digest.hexdigest()


def check_task(name: str, trained: FormationConfig, wanted: FormationConfig, where: str, any_team_size: bool) -> None:
    """Refuse to act in a task other than the one a shipped policy was trained for.

    :param where: what asked for ``wanted`` (e.g. ``recipe ch4-team``), for the message
    :param any_team_size: the policy was trained on teams of several sizes, so ``n_agents`` may differ
    :raises ValueError: naming every differing field
    """
    free = FREE_FIELDS | ({"n_agents"} if any_team_size else set())
    differences = [
        f"{field}={getattr(wanted, field)!r} (trained with {getattr(trained, field)!r})"
        for field in trained.__dataclass_fields__
        if field not in free and getattr(trained, field) != getattr(wanted, field)
    ]
    if differences:
        raise ValueError(
            f"pretrained:{name} was not trained for {where}: {'; '.join(differences)}; "
            f"evaluate it without --recipe (its own task) or train a policy for that task"
        )


def load_pretrained(
    name: str, recipe: str | None = None, device: str = "cpu", root: Path = PRETRAINED_DIR, trusted: bool | None = None
) -> TeamPolicy:
    """A shipped policy, ready to act (a :class:`~sb3_formation.sb3.trained.TrainedPolicy`, or a residual policy
    around one).

    :param name: one of :func:`pretrained_names` (``sb3-formation pretrained`` lists them)
    :param recipe: a recipe whose task it must act in; refused unless it is the task the policy was trained for
    :param device: torch device
    :param trusted: unpickle what its model file needs (see :func:`~sb3_formation.experiment.runs.load_trained`;
        the shipped files need nothing of it)
    :raises ValueError: an unknown name, or a recipe of another task
    """
    policy = load_trained(pretrained_folder(name, root), device=device, trusted=trusted)
    if recipe is not None:
        sizes = pretrained_card(name, root).get("team_sizes", [policy.config.n_agents])
        check_task(name, policy.config, load_recipe(recipe).config(), f"recipe {recipe}", len(sizes) > 1)
    return policy
