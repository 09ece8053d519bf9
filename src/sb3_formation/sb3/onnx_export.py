"""Exporting a trained policy's actor to ONNX, for :class:`~sb3_formation.runtime.OnnxPolicy` (``docs/export.md``).

The graph computes what :meth:`TrainedPolicy.predict <sb3_formation.sb3.trained.TrainedPolicy.predict>` computes
deterministically, from one agent's raw observation: the frozen normaliser (in float64, as numpy does it), the actor
(dense layers, or dense, recurrent and dense layers with the state as input and output), the bounded mean action and
the clip to the action space; a policy whose agents send messages also reads the messages its ring neighbours sent
(``message_in``) and returns the one it sends (``message_out``). Only the actor is exported: a team critic is a
training device (the actor reads the agent's own observation). A residual policy's controller stays numpy: the graph is
the correction, and the metadata name the controller, its gains and the scale, which the runtime composes
(``docs/export.md`` says why).
"""

from __future__ import annotations

import json
import logging
import math
import os
import warnings
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy
from sb3_formation.runtime.onnx_policy import GRAPH_DIGEST_KEY, PolicyMetadata, graph_digest
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.normalization import observation_offset, observation_scale
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.utils.files import atomic_path

#: The ONNX opset the graph is written in (onnxruntime 1.14 and later run it).
DEFAULT_OPSET = 18
#: The opsets an export may ask for: torch's exporter writes 18 and converts to 19-25 without a fallback (measured with
#: torch 2.13 and onnxscript); below 18 it falls back to onnx's converter with warnings, and silently writes 18 for
#: opsets it does not know.
SUPPORTED_OPSETS = range(18, 26)
#: Rows of the example batch the graph is traced with (its batch dimension stays free).
EXAMPLE_ROWS = 2


class ActorGraph(nn.Module):
    """A trained policy's deterministic actor on raw observations: what the exported graph computes.

    :param trained: the trained policy (an MLP :class:`FormationPolicy`, with or without a team critic, or a
        :class:`RecurrentFormationPolicy`)
    :raises ValueError: a policy of another kind, or with a features extractor other than SB3's flattening one
    """

    # buffers (register_buffer)
    scale: th.Tensor
    offset: th.Tensor
    low: th.Tensor
    high: th.Tensor

    def __init__(self, trained: TrainedPolicy) -> None:
        super().__init__()
        policy = trained.policy
        if not isinstance(policy, (FormationPolicy, RecurrentFormationPolicy)):
            raise ValueError(
                f"export_onnx exports FormationPolicy and RecurrentFormationPolicy models, not {type(policy).__name__}"
            )
        if not isinstance(policy.features_extractor, FlattenExtractor):
            raise ValueError(f"cannot export a policy whose features extractor is {type(policy.features_extractor).__name__}")
        state = trained.normalizer_state
        offset = observation_offset(state)
        self.register_buffer("scale", th.as_tensor(observation_scale(state), dtype=th.float64))
        self.register_buffer(
            "offset", th.as_tensor(np.zeros_like(state["var"]) if offset is None else offset, dtype=th.float64)
        )
        clip = float(state["clip_obs"])
        self.clip = None if math.isnan(clip) else clip
        self.recurrent = isinstance(policy, RecurrentFormationPolicy)
        self.memory, self.message_size, self.message_net = False, 0, None
        if self.recurrent:
            recurrent = cast(RecurrentFormationPolicy, policy)
            actor = recurrent.actor
            self.before, self.rnn, self.after = actor.before, actor.rnn, actor.after
            self.cell, self.hidden = actor.cell, actor.hidden
            self.memory, self.message_size, self.message_net = recurrent.memory, recurrent.message_size, recurrent.message_net
        else:  # MlpExtractor's, or TeamCriticExtractor's on the own block
            self.body = cast(FormationPolicy, policy).mlp_extractor.policy_net
        self.action_net, self.action_scale = policy.action_net, policy.action_scale
        box = cast(spaces.Box, policy.action_space)  # Gaussian actions
        self.register_buffer("low", th.as_tensor(box.low, dtype=th.float32))
        self.register_buffer("high", th.as_tensor(box.high, dtype=th.float32))

    def forward(self, observation: th.Tensor, *inputs: th.Tensor) -> th.Tensor | tuple[th.Tensor, ...]:
        """The clipped mean action of each row (and, recurrent with memory, the actor's next state; with messages, the
        message each row sends).

        :param observation: ``(batch, obs_dim)`` float32 raw observations
        :param inputs: a recurrent actor's state with memory, ``(1, batch, hidden)`` each (``h``; ``h, c`` for an
            LSTM); then, with messages, ``(batch, 2 M)`` the messages of each row's preceding and succeeding neighbours
        """
        scaled = (observation.double() - self.offset) / self.scale
        if self.clip is not None:
            scaled = scaled.clamp(-self.clip, self.clip)
        scaled = scaled.float()
        if not self.recurrent:
            latent = self.body(scaled)
            return th.clamp(self.action_scale * th.tanh(self.action_net(latent)), self.low, self.high)
        parts = (1 if self.cell == "gru" else 2) if self.memory else 0
        state = inputs[:parts] or (scaled.new_zeros(1, scaled.shape[0], self.hidden),) * (1 if self.cell == "gru" else 2)
        features = self.before(th.cat([scaled, inputs[parts]], dim=-1) if self.message_size else scaled)
        outputs, final = self.rnn(features.unsqueeze(0), state[0] if self.cell == "gru" else state)
        latent = self.after(outputs[0])
        action = th.clamp(self.action_scale * th.tanh(self.action_net(latent)), self.low, self.high)
        state_out = ((final,) if self.cell == "gru" else tuple(final)) if self.memory else ()
        message = (th.tanh(self.message_net(latent)),) if self.message_net is not None else ()
        return (action, *state_out, *message)


def _parts(policy: TeamPolicy) -> tuple[TrainedPolicy, dict[str, Any] | None, dict[str, Any] | None]:
    """The trained policy to export; for a residual policy its ``controller``, ``gains`` and ``scale``; for a policy
    behind the safety filter the filter's gains."""
    residual, safety = None, None
    if isinstance(policy, SafePolicy):
        filtered: SafePolicy = policy
        policy, safety = filtered.policy, filtered.filter.gains.to_dict()
    if isinstance(policy, ResidualPolicy):
        names = [name for name, kind in CONTROLLERS.items() if type(policy.base) is kind]
        if not names:
            raise ValueError(
                f"the residual policy's controller {type(policy.base).__name__} is not one of {sorted(CONTROLLERS)}"
            )
        residual = {"controller": names[0], "gains": dict(policy.base.gains), "scale": policy.scale}
        policy = policy.correction
    if not isinstance(policy, TrainedPolicy):
        raise ValueError(
            f"only trained policies can be exported to ONNX, not {type(policy).__name__} (controllers are numpy code)"
        )
    return policy, residual, safety


def export_onnx(policy: TeamPolicy, path: str | os.PathLike[str], opset: int = DEFAULT_OPSET) -> Path:
    """Write a trained policy's actor as an ONNX model that :class:`~sb3_formation.runtime.OnnxPolicy` runs.

    :param policy: a :class:`TrainedPolicy` or a residual policy around one (what ``load_policy`` returns for a run
        folder, a model file or ``pretrained:<name>``), possibly behind the safety filter (a shielded run's, or
        ``safe:<target>``): the file then carries the filter's gains and its runtime filters its actions
    :param path: the ``.onnx`` file to write (replaced only once complete)
    :param opset: the ONNX opset
    :return: ``path``
    :raises ValueError: an opset outside :data:`SUPPORTED_OPSETS`, a policy that is not a trained one, or of a kind
        the graph cannot hold
    :raises ImportError: onnx or onnxscript (which torch's exporter needs) is not installed
    """
    if opset not in SUPPORTED_OPSETS:
        raise ValueError(
            f"opset must be {SUPPORTED_OPSETS[0]}-{SUPPORTED_OPSETS[-1]} (what torch's exporter writes), got {opset!r}"
        )
    try:
        import onnx
        import onnxscript  # noqa: F401  (torch.onnx's exporter imports it; say so before tracing)
    except ImportError:
        raise ImportError("exporting to ONNX needs onnx and onnxscript: pip install 'sb3-formation[export]'") from None
    trained, residual, safety = _parts(policy)
    graph = ActorGraph(trained).cpu().eval()
    recurrent = {"cell": graph.cell, "hidden": graph.hidden} if graph.memory else None
    metadata = PolicyMetadata(trained.config, tuple(trained.team_sizes), residual, recurrent, safety, graph.message_size)
    batch = th.export.Dim("batch")
    observation = th.zeros(EXAMPLE_ROWS, metadata.observation_dim)
    state = tuple(th.zeros(1, EXAMPLE_ROWS, graph.hidden) for _ in metadata.state_parts)
    received = (th.zeros(EXAMPLE_ROWS, 2 * graph.message_size),) if graph.message_size else ()
    extra = tuple({1: batch} for _ in state) + tuple({0: batch} for _ in received)
    dynamic_shapes = ({0: batch}, extra) if extra else ({0: batch},)
    exporter_log = logging.getLogger("torch.onnx")
    level = exporter_log.level
    with warnings.catch_warnings(), th.no_grad():
        warnings.simplefilter("ignore")  # the exporter's notes on its own internals (and on torchvision's operators)
        exporter_log.setLevel(logging.ERROR)
        try:
            program = th.onnx.export(
                graph,
                (observation, *state, *received),
                dynamo=True,
                dynamic_shapes=dynamic_shapes,
                input_names=metadata.input_names,
                output_names=metadata.output_names,
                opset_version=opset,
                verbose=False,
            )
        finally:
            exporter_log.setLevel(level)
    assert program is not None  # dynamo=True returns the program
    model = program.model_proto
    written = next(entry.version for entry in model.opset_import if entry.domain in ("", "ai.onnx"))
    if written != opset:
        raise RuntimeError(f"torch's exporter wrote opset {written} where {opset} was asked: nothing was written")
    metadata = PolicyMetadata(trained.config, metadata.team_sizes, residual, recurrent, safety, graph.message_size, written)
    onnx.helper.set_model_props(model, {**metadata.to_properties(), GRAPH_DIGEST_KEY: json.dumps(graph_digest(model))})
    model.producer_name = "sb3-formation"
    path = Path(path)
    with atomic_path(path) as temporary:
        onnx.save_model(model, str(temporary))
    return path
