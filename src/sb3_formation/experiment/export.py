"""Making a shipped policy (:mod:`sb3_formation.experiment.pretrained`) of a finished training run, its ONNX export
included."""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import shutil
from pathlib import Path
from typing import cast

import stable_baselines3
import torch

from sb3_formation import __version__
from sb3_formation.experiment.evaluation import EVALUATION_TEAMS, evaluate
from sb3_formation.experiment.pretrained import CARD_FILE, ONNX_FILE, PRETRAINED_DIR, SUMMARY_PATH, numerics_fingerprint
from sb3_formation.experiment.recipes import load_settings
from sb3_formation.experiment.runs import (
    FINAL_MODEL,
    FINAL_NORMALIZER,
    latest_checkpoint,
    load_trained,
    read_state,
)
from sb3_formation.sb3.model_files import load_model
from sb3_formation.sb3.onnx_export import export_onnx
from sb3_formation.utils.files import atomic_directory, folder_lock, package_writes

#: Attributes of a saved model that acting does not need (the last rollout's observations, episode buffers).
UNSHIPPED_ATTRIBUTES = ("_last_obs", "_last_original_obs", "_last_episode_starts", "ep_info_buffer", "ep_success_buffer")


def export_pretrained(
    run_dir: str | os.PathLike[str],
    name: str,
    root: Path = PRETRAINED_DIR,
    command: str | None = None,
    progress_bar: bool = False,
    replace: bool = False,
) -> Path:
    """Make a shipped policy of a finished run: trim its final model, export it to ONNX, evaluate the model file on the
    run's protocol, and write the folder (replacing one of the same name, when told to, only once all of it is
    written).

    :param run_dir: a run folder with ``final_model.zip``, ``final_normalizer.npz`` and its last checkpoint
    :param name: the policy's name (``pretrained:<name>``): letters, digits, ``-`` and ``_``
    :param root: the folder of shipped policies (default: the package's)
    :param command: the command that exported it, recorded in the card
    :param progress_bar: show the evaluation's progress bar
    :param replace: replace a policy of that name in ``root`` (else it is an error)
    :return: the policy's folder
    """
    if not name or not all(character.isalnum() or character in "-_" for character in name):
        raise ValueError(f"a shipped policy's name is letters, digits, '-' and '_', got {name!r}")
    run_dir = Path(run_dir)
    settings = load_settings(run_dir)
    checkpoint = latest_checkpoint(run_dir)
    missing = [file for file in (FINAL_MODEL, FINAL_NORMALIZER) if not (run_dir / file).is_file()]
    if missing or checkpoint is None:
        raise ValueError(f"{run_dir} is not a finished run: it lacks {', '.join(missing) or 'a checkpoint'}")
    state = read_state(checkpoint)
    protocol = settings.recipe.evaluation.replace(record=0)
    if (root / name).exists() and not replace:
        raise ValueError(f"pretrained:{name} exists in {root}: give another name, or --replace to replace it")
    with package_writes(), folder_lock(root, "folder of shipped policies", remove=True):
        for leftover in root.glob(f".{name}.*"):  # the temporary folder of an export that was killed
            if not leftover.name.startswith(f".{name}.old."):  # (a folder renamed aside: atomic_directory restores it)
                shutil.rmtree(leftover, ignore_errors=True)
        with atomic_directory(root / name) as folder:
            model = load_model(run_dir / FINAL_MODEL, device="cpu")  # nothing in the run's files is unpickled
            policy = model.policy
            trained = [parameter for group in policy.optimizer.param_groups for parameter in group["params"]]
            # an empty state over the parameters it trained (a fixed sigma's log-std is not one)
            policy.optimizer = policy.optimizer_class(trained, **policy.optimizer.defaults)
            model.save(folder / FINAL_MODEL, exclude=list(UNSHIPPED_ATTRIBUTES))
            shutil.copyfile(run_dir / FINAL_NORMALIZER, folder / FINAL_NORMALIZER)
            shutil.copyfile(run_dir / "config.yaml", folder / "config.yaml")
            shipped = load_trained(folder, device="cpu")
            export_onnx(shipped, folder / ONNX_FILE)
            result = evaluate(shipped, **protocol.kwargs(), progress_bar=progress_bar)
            # the summary names the shipped model (its SHA-256), not the temporary folder it was evaluated in
            result = dataclasses.replace(result, model={**cast("dict[str, str]", result.model), "file": f"pretrained:{name}"})
            result.save((folder / SUMMARY_PATH).parent)
            card = {
                "name": name,
                "recipe": settings.recipe.name,
                "n_agents": settings.recipe.config().n_agents,
                "team_sizes": sorted(set(settings.recipe.sizes)),
                "seed": settings.run.seed,
                "training_command": (run_dir / "command.txt").read_text().strip(),
                "export_command": command,
                "training_seconds": round(float(state["training_seconds"]), 1),
                "training_agent_steps": int(state["num_timesteps"]),
                "package_version": __version__,
                "versions": {
                    "stable_baselines3": stable_baselines3.__version__,
                    "torch": torch.__version__,
                    "python": platform.python_version(),
                },
                "exported": datetime.date.today().isoformat(),
                # teams played at once: a replay plays as many
                "evaluation_teams": EVALUATION_TEAMS if protocol.n_envs is None else protocol.n_envs,
                "numerics": numerics_fingerprint(),  # where a machine's is the same, the stored episodes replay exactly
            }
            (folder / CARD_FILE).write_text(json.dumps(card, indent=2) + "\n")
    return root / name
