"""Reading Stable-Baselines3 model files without running code from them.

SB3 writes a model as a zip file: ``policy.pth`` (and ``policy.optimizer.pth``, ``pytorch_variables.pth``) hold
tensors, read here with ``torch.load(..., weights_only=True)``; ``data`` is JSON in which every value that is not plain
JSON (classes, schedules, spaces, buffers) is a pickle (``":serialized:"``) that SB3's ``load`` unpickles, running
whatever the file's author put there. :func:`load_model` reads ``data`` as JSON only and rebuilds what it needs from
plain values: the policy class from an allow-list (:data:`POLICY_CLASSES`, named by the plain reference SB3's pickle of
a class is), the schedules from the numbers SB3 writes beside their pickles, the spaces from the recorded task. A file
that needs unpickling for any of these is refused, unless its loading is trusted (``trusted=True``, or inside
:func:`trust_pickle`): then SB3's own ``load`` reads it, after saying what it unpickles.
"""

from __future__ import annotations

import ast
import base64
import binascii
import contextvars
import io
import json
import math
import pickle
import pickletools
import re
import sys
import zipfile
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import recursive_setattr
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule, LinearSchedule, get_device
from stable_baselines3.common.vec_env import VecEnv

from sb3_formation.controllers.base import observation_size
from sb3_formation.env.config import FormationConfig
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy, RecurrentFormationPPO
from sb3_formation.utils.files import oversized_entry

#: The policy classes a model file may name when it is not trusted, by module and qualified name.
POLICY_CLASSES: dict[str, type[BasePolicy]] = {
    f"{policy.__module__}.{policy.__qualname__}": policy for policy in (FormationPolicy, RecurrentFormationPolicy)
}
#: SB3's schedule classes, rebuilt from the numbers written beside their pickles (or from their text).
SCHEDULES: dict[str, type] = {schedule.__name__: schedule for schedule in (ConstantSchedule, FloatSchedule, LinearSchedule)}
#: Settings that are schedules: read from plain numbers or SB3's schedule classes.
SCHEDULE_SETTINGS = ("learning_rate", "clip_range", "clip_range_vf")
#: Counters of a saved model that a resumed training continues from.
COUNTERS = ("num_timesteps", "_total_timesteps", "_num_timesteps_at_start", "_episode_num", "_n_updates")
#: Settings of a checkpoint that must be the run recipe's for a resume from it to continue the same training.
TRAINING_SETTINGS = (
    *("n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "ent_coef", "vf_coef", "max_grad_norm"),
    *("normalize_advantage", "target_kl", "seed", "max_sequence_length", "policy_kwargs"),
)
#: Attributes a model's construction decides, never taken from a file's data.
CONSTRUCTED = ("policy_class", "rollout_buffer_class", "observation_space", "action_space", "lr_schedule", "device", "env")
#: Attribute of a saved model holding the episode windows of SB3's rollout statistics as plain JSON (SB3 pickles them).
EPISODE_WINDOWS = "episode_windows"
#: The opcodes of a pickle that only names a global (a class): nothing is called or built when it is read.
_REFERENCE_OPCODES = frozenset({"PROTO", "FRAME", "MEMOIZE", "PUT", "BINPUT", "LONG_BINPUT"})
_STRING_OPCODES = frozenset({"SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"})

_trusted: contextvars.ContextVar[bool] = contextvars.ContextVar("trusted_model_files", default=False)


@contextmanager
def trust_pickle(trusted: bool | None = True) -> Iterator[None]:
    """Within it, model files loaded without an explicit ``trusted`` are trusted (``None``: leave it as it is).

    :param trusted: whether to unpickle what model files need
    """
    token = None if trusted is None else _trusted.set(bool(trusted))
    try:
        yield
    finally:
        if token is not None:
            _trusted.reset(token)


def is_trusted(trusted: bool | None = None) -> bool:
    """``trusted``, or where it is ``None`` whether the caller is inside :func:`trust_pickle`."""
    return _trusted.get() if trusted is None else bool(trusted)


def read_model_data(path: Path) -> dict[str, Any]:
    """The ``data`` of a model file as plain JSON (nothing in it is unpickled).

    :raises FileNotFoundError: no file at ``path``
    :raises ValueError: not a model saved by Stable-Baselines3
    """
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path}")
    try:
        with zipfile.ZipFile(path) as archive:
            if problem := oversized_entry(archive):
                raise ValueError(problem)
            data = json.loads(archive.read("data").decode())
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as error:
        raise ValueError(f"{path} is not a model saved by Stable-Baselines3: {error}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} is not a model saved by Stable-Baselines3: its data is not a mapping")
    return data


def is_serialized(value: Any) -> bool:
    """Whether a value of a model file's data is SB3's pickle of an object, or holds one."""
    if isinstance(value, dict):
        return ":serialized:" in value or any(is_serialized(item) for item in value.values())
    return isinstance(value, list) and any(is_serialized(item) for item in value)


def serialized_names(data: dict[str, Any]) -> list[str]:
    """The entries of a model file's data that SB3's ``load`` unpickles."""
    return [name for name, value in data.items() if is_serialized(value)]


def class_reference(serialized: str) -> str | None:
    """``module.qualname`` of the class a pickle names, read without unpickling, or ``None`` if the pickle does
    anything but name one global (SB3 pickles a class as such a reference)."""
    try:
        operations = [(opcode.name, argument) for opcode, argument, _ in pickletools.genops(base64.b64decode(serialized))]
    except (ValueError, binascii.Error):
        return None
    steps = [(name, argument) for name, argument in operations if name not in _REFERENCE_OPCODES]
    if [name for name, _ in steps] == ["GLOBAL", "STOP"]:
        return str(steps[0][1]).replace(" ", ".", 1)
    if len(steps) == 4 and all(name in _STRING_OPCODES for name, _ in steps[:2]):
        if [name for name, _ in steps[2:]] == ["STACK_GLOBAL", "STOP"]:
            return f"{steps[0][1]}.{steps[1][1]}"
    return None


def policy_class_name(data: dict[str, Any]) -> str | None:
    """``module.qualname`` of the policy class a model file names, read without unpickling (``None``: none readable)."""
    entry = data.get("policy_class")
    if not (isinstance(entry, dict) and isinstance(entry.get(":serialized:"), str)):
        return None
    name = class_reference(entry[":serialized:"])
    module = entry.get("__module__")
    return name if name is not None and (module is None or name.startswith(f"{module}.")) else None


def policy_class_of(data: dict[str, Any]) -> type[BasePolicy] | None:
    """The policy class of a model file if it is one of :data:`POLICY_CLASSES`, else ``None``."""
    return POLICY_CLASSES.get(policy_class_name(data) or "")


def algorithm_for(policy: type | None) -> type[PPO]:
    """The PPO class that trains ``policy``: :class:`RecurrentFormationPPO` for a recurrent policy, else SB3's ``PPO``."""
    return RecurrentFormationPPO if isinstance(policy, type) and issubclass(policy, RecurrentFormationPolicy) else PPO


def plain_schedule(value: Any) -> float | Schedule | None:
    """A learning rate or clip range of a model file's data from plain values: a number, or one of SB3's schedules
    (:data:`SCHEDULES`, or this package's clocked schedule, saved as the schedule it wraps) from the numbers or text
    SB3 writes beside its pickle; ``None`` if it cannot be read so."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if not (isinstance(value, dict) and ":serialized:" in value):
        return None
    kind = re.fullmatch(r"<class '([\w.]+)'>", str(value.get(":type:")))
    name = kind.group(1).rpartition(".")[2] if kind else ""
    fields = {key: item for key, item in value.items() if not key.startswith(":")}
    if name in ("FloatSchedule", "ClockedSchedule"):
        inner = schedule_from_text(str(fields.get("value_schedule", fields.get("schedule", ""))))
        return None if inner is None else FloatSchedule(inner)
    return schedule_from_text(f"{name}(**{fields!r})") if name in SCHEDULES else None


def schedule_from_text(text: str) -> Schedule | None:
    """One of SB3's schedules from its text (``LinearSchedule(start=0.1, end=0.01, end_fraction=1.0)``, also nested in
    ``FloatSchedule(...)``), parsed as literals (nothing is evaluated); ``None`` if it is not such text."""
    try:
        return _schedule_from_node(ast.parse(text, mode="eval").body)
    except (SyntaxError, ValueError, TypeError, RecursionError):  # not such text, or nested without end
        return None


def _schedule_from_node(node: ast.AST) -> Schedule | None:
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in SCHEDULES):
        return None
    arguments = [_schedule_from_node(item) or ast.literal_eval(item) for item in node.args]
    keywords: dict[str, Any] = {}
    for keyword in node.keywords:
        values = ast.literal_eval(keyword.value)
        keywords.update(values if keyword.arg is None else {keyword.arg: values})
    numbers = [*arguments, *keywords.values()]
    if not all(callable(item) or (isinstance(item, (int, float)) and math.isfinite(item)) for item in numbers):
        return None
    return SCHEDULES[node.func.id](*arguments, **keywords)


def unreadable_settings(data: dict[str, Any]) -> list[str]:
    """What of a model file's data only unpickling would give: an unknown policy class, policy keyword arguments
    that are not plain (e.g. a custom ``activation_fn`` or ``features_extractor_class``), schedules that are not
    SB3's."""
    problems = []
    if policy_class_of(data) is None:
        named = policy_class_name(data) or "not a plain class reference"
        problems.append(f"policy_class ({named}; allowed: {', '.join(POLICY_CLASSES)})")
    kwargs = data.get("policy_kwargs", {})
    if not isinstance(kwargs, dict) or is_serialized(kwargs):
        problems.append("policy_kwargs (values that are not plain data)")
    problems += [name for name in SCHEDULE_SETTINGS if data.get(name) is not None and plain_schedule(data.get(name)) is None]
    return problems


def refusal(path: Path, problems: list[str]) -> str:
    """The one-line refusal of a model file whose loading needs unpickling."""
    return (
        f"{path} needs unpickling to load ({'; '.join(problems)}), which runs code from the file: load it only if "
        "you trust it, with --trust-pickle (trusted=True in Python)"
    )


def observation_space_of(config: FormationConfig, team_size: int | None) -> spaces.Box:
    """The observation space a model of ``config`` reads: each slot's observation (followed, with a team critic, by
    its team's), of the env's size; unbounded, since scaled observations have no bounds of their own."""
    size = observation_size(config) * (1 + (team_size or 0))
    return spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)


def recorded_config(path: Path, data: dict[str, Any]) -> FormationConfig:
    """The task configuration a model file records.

    :raises ValueError: it records none
    """
    if not isinstance(data.get("formation_config"), dict):
        raise ValueError(f"{path} was not saved by sb3-formation: it carries no formation_config")
    return FormationConfig.from_dict(data["formation_config"])


def load_model(path: Path, device: str = "auto", trusted: bool | None = None, env: VecEnv | None = None) -> PPO:
    """A model file as SB3's ``load`` gives it, without unpickling anything unless trusted.

    :param path: a model ``.zip`` saved by sb3-formation
    :param device: torch device
    :param trusted: unpickle what the file needs, with SB3's ``load`` (``None``: as :func:`trust_pickle` says)
    :param env: for trusted loading, the env to attach (as SB3's ``load``)
    :raises ValueError: the file needs unpickling and is not trusted, or is not a model of this package
    """
    data = read_model_data(path)
    if is_trusted(trusted):
        return trusted_load(path, data, device, env)
    if env is not None:
        raise ValueError("load_model attaches an env only in trusted loading; a resume rebuilds the model instead")
    problems = unreadable_settings(data)
    if problems:
        raise ValueError(refusal(path, problems))
    config = recorded_config(path, data)
    policy_class = policy_class_of(data)
    kwargs = data.get("policy_kwargs", {})
    # SB3 builds an algorithm without an env when _init_setup_model is False, and unreadable_settings has checked the
    # policy class; SB3's annotations ask for an env and an ActorCriticPolicy class
    model = algorithm_for(policy_class)(policy=policy_class, env=None, device=device, _init_setup_model=False)  # type: ignore[arg-type]
    model.__dict__.update(
        {name: value for name, value in data.items() if name not in CONSTRUCTED and not is_serialized(value)}
    )
    model.__dict__.update({name: plain_schedule(data[name]) for name in SCHEDULE_SETTINGS if data.get(name) is not None})
    model.observation_space = observation_space_of(config, kwargs.get("team_size"))
    model.action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
    model._setup_model()
    load_parameters(model, path, device)
    return model


def trusted_load(path: Path, data: dict[str, Any], device: str, env: VecEnv | None) -> PPO:
    """SB3's ``load`` of a trusted file, after saying on stderr what it unpickles."""
    print(f"sb3-formation: trusting {path}: unpickling {', '.join(serialized_names(data))}", file=sys.stderr)
    return algorithm_for(policy_class_of(data)).load(path, env=env, device=device)


def read_tensors(path: Path, device: str | th.device = "auto") -> dict[str, Any]:
    """The ``.pth`` members of a model file by name (``policy``, ``policy.optimizer``, ``pytorch_variables``), read
    with ``torch.load(..., weights_only=True)``: tensors and plain containers only.

    :raises ValueError: a member holds anything else, or the file is damaged
    """
    tensors = {}
    try:
        with zipfile.ZipFile(path) as archive:
            if problem := oversized_entry(archive):
                raise ValueError(f"{path} is not a model saved by Stable-Baselines3: {problem}")
            for name in (member for member in archive.namelist() if member.endswith(".pth")):
                stream = io.BytesIO(archive.read(name))
                tensors[name.removesuffix(".pth")] = th.load(stream, map_location=get_device(device), weights_only=True)
    except (zipfile.BadZipFile, pickle.UnpicklingError, RuntimeError, OSError) as error:
        raise ValueError(f"{path} holds tensors that cannot be read as weights only: {error}".splitlines()[0]) from None
    return tensors


def load_parameters(model: BaseAlgorithm, path: Path, device: str | th.device = "auto") -> None:
    """Put a model file's tensors (:func:`read_tensors`) into ``model``, as SB3's ``load`` does."""
    tensors = read_tensors(path, device)
    variables = tensors.pop("pytorch_variables", None) or {}
    model.set_parameters(tensors, exact_match=True, device=device)
    for name, value in variables.items():
        if value is not None:
            recursive_setattr(model, f"{name}.data", value.data)


def restore_training_state(model: PPO, path: Path) -> None:
    """Continue ``model``, built from its run's recipe, from a checkpoint file: its tensors (policy and optimiser),
    counters and episode windows, read without unpickling.

    :raises ValueError: the checkpoint was trained with other settings than ``model``'s
    """
    data = read_model_data(path)
    problems = [problem for problem in unreadable_settings(data) if problem not in SCHEDULE_SETTINGS]  # the recipe's
    if problems:
        raise ValueError(refusal(path, problems))
    if policy_class_of(data) is not model.policy_class:
        raise ValueError(f"{path} holds a {policy_class_name(data)}, its run's recipe a {model.policy_class.__name__}")
    differences = [
        f"{name}={data[name]!r} in the checkpoint, {getattr(model, name)!r} in the recipe"
        for name in TRAINING_SETTINGS
        if name in data and not is_serialized(data[name]) and data[name] != _plain(getattr(model, name, None))
    ]
    if differences:
        raise ValueError(f"{path} was trained with other settings than its run's recipe: {'; '.join(differences)}")
    load_parameters(model, path, model.device)
    model.__dict__.update({name: data[name] for name in COUNTERS if isinstance(data.get(name), int)})
    if isinstance(data.get("_current_progress_remaining"), (int, float)):
        model._current_progress_remaining = float(data["_current_progress_remaining"])
    windows = data.get(EPISODE_WINDOWS)
    if isinstance(windows, dict):
        model.ep_info_buffer = deque(windows.get("ep_info_buffer", []), maxlen=model._stats_window_size)
        model.ep_success_buffer = deque(windows.get("ep_success_buffer", []), maxlen=model._stats_window_size)


def record_episode_windows(model: BaseAlgorithm) -> None:
    """Keep SB3's episode windows (the last episodes' returns, lengths and successes, which SB3 pickles) in a plain
    attribute saved with the model, so a resume continues its rolling statistics without unpickling."""
    windows = {
        name: [_plain(item) for item in getattr(model, name, None) or ()] for name in ("ep_info_buffer", "ep_success_buffer")
    }
    setattr(model, EPISODE_WINDOWS, windows)


def _plain(value: Any) -> Any:
    """``value`` with numpy scalars as Python numbers and tuples as lists (as JSON reads them back)."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value.item() if isinstance(value, np.generic) else value
