"""A policy exported to ONNX (``sb3-formation export``), run with onnxruntime: numpy and onnxruntime only, no torch.

The graph (``docs/export.md``) reads the raw observations of one agent or a batch, ``observation`` ``(batch, obs_dim)``
float32, folds in the frozen scale-only normaliser, and returns the clipped action ``action`` ``(batch, 2)``; a
recurrent policy also reads and returns its actor's state (``hidden_in`` -> ``hidden_out``, and for an LSTM
``cell_in`` -> ``cell_out``, each ``(1, batch, hidden)``). A residual policy's graph returns the network's
``correction``; a policy whose agents send messages also reads the messages of each row's ring neighbours,
``message_in`` ``(batch, 2 M)`` (preceding then succeeding), and returns the one each row sends, ``message_out``
``(batch, M)``. :class:`OnnxPolicy` adds a residual policy's correction to the numpy controller's action the metadata
names (the residual composition of ``docs/export.md``) with :class:`~sb3_formation.controllers.residual.ResidualAdapter`,
as training and evaluation do. The model's metadata (:class:`PolicyMetadata`) hold the task configuration, the
observation layout, the team sizes, the residual, recurrent, safety and message settings, the package version and the
opset. An :class:`OnnxPolicy` never filters its actions: :func:`load_onnx_policy` puts a policy trained behind the
safety filter behind :class:`~sb3_formation.safety.policy.SafePolicy`, with the gains its metadata record.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from sb3_formation import __version__
from sb3_formation.controllers import ResidualAdapter, controller_from_spec
from sb3_formation.controllers.base import (
    AgentStep,
    Policy,
    TeamPolicy,
    cell_state,
    check_fit,
    no_messages,
    observation_size,
    state_pair,
)
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.safety.filter import SafetyGains
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.utils.files import MAX_FILE_BYTES

#: Prefix of the metadata keys this package writes into an exported model.
METADATA_PREFIX = "sb3_formation."
#: Version of the graph's contract (inputs, outputs, metadata keys); a runtime refuses other versions.
FORMAT_VERSION = 2
#: Metadata key of the SHA-256 of the serialised graph (nodes and weights): a file changed since its export is refused.
GRAPH_DIGEST_KEY = METADATA_PREFIX + "graph_sha256"
#: Name of the graph's observation input.
OBSERVATION_INPUT = "observation"
#: Name of the graph's first output: the action, or a residual policy's correction.
ACTION_OUTPUT, CORRECTION_OUTPUT = "action", "correction"
#: Names of the graph's message input (what each row's ring neighbours sent) and output (what each row sends).
MESSAGE_INPUT, MESSAGE_OUTPUT = "message_in", "message_out"
#: The actor state's parts of each recurrent cell, as the graph names them (``<part>_in`` / ``<part>_out``).
STATE_PARTS = {"gru": ("hidden",), "lstm": ("hidden", "cell")}
#: The most elements any tensor of an exported graph may have (:func:`check_graph`): a quarter of
#: :data:`~sb3_formation.utils.files.MAX_FILE_BYTES`, i.e. that many bytes of float32.
MAX_TENSOR_ELEMENTS = MAX_FILE_BYTES // 4


@dataclass(frozen=True)
class PolicyMetadata:
    """What an exported graph records of its policy, as the model's metadata (string values, JSON where structured).

    :param config: the task configuration it was trained in
    :param team_sizes: the team sizes it was trained on (several: it acts in teams of any size)
    :param residual: ``controller``, ``gains`` and ``scale`` of a residual policy (the graph is its correction), or
        ``None``
    :param recurrent: ``cell`` (``gru`` / ``lstm``) and ``hidden`` (width of its state) of a recurrent actor, or ``None``
    :param safety: the safety filter's gains of a policy trained behind it (its actions are filtered wherever it runs),
        or ``None``; files written before the filter existed have no such key and read as ``None``
    :param message_size: M, the values of the message each agent sends its ring neighbours every step (0: none; files
        of policies without messages may lack the key)
    :param opset: the ONNX opset of the graph
    :param package_version: the version of sb3-formation that exported it
    """

    config: FormationConfig
    team_sizes: tuple[int, ...]
    residual: dict[str, Any] | None = None
    recurrent: dict[str, Any] | None = None
    safety: dict[str, Any] | None = None
    message_size: int = 0
    opset: int = 0
    package_version: str = __version__

    @property
    def observation_dim(self) -> int:
        """Features of one agent's observation."""
        return observation_size(self.config)

    @property
    def state_parts(self) -> tuple[str, ...]:
        """The actor state's parts (``()`` for a feed-forward policy)."""
        return () if self.recurrent is None else STATE_PARTS[self.recurrent["cell"]]

    @property
    def input_names(self) -> list[str]:
        """The graph's inputs, in order."""
        return [
            OBSERVATION_INPUT,
            *(f"{part}_in" for part in self.state_parts),
            *([MESSAGE_INPUT] if self.message_size else []),
        ]

    @property
    def output_names(self) -> list[str]:
        """The graph's outputs, in order."""
        first = CORRECTION_OUTPUT if self.residual is not None else ACTION_OUTPUT
        return [first, *(f"{part}_out" for part in self.state_parts), *([MESSAGE_OUTPUT] if self.message_size else [])]

    def to_properties(self) -> dict[str, str]:
        """The metadata as the model's ``metadata_props`` (key -> string)."""
        fields = observation_fields(self.config)
        layout = [
            {"name": field.name, "start": where.start, "stop": where.stop, "binary": field.binary}
            for field, where in zip(fields, observation_layout(fields).values())
        ]
        values = {
            "format": FORMAT_VERSION,
            "config": self.config.to_dict(),
            "observation_layout": layout,
            "team_sizes": list(self.team_sizes),
            "residual": self.residual,
            "recurrent": self.recurrent,
            "safety": self.safety,
            "message_size": self.message_size,
            "opset": self.opset,
            "package_version": self.package_version,
        }
        return {METADATA_PREFIX + key: json.dumps(value) for key, value in values.items()}

    @classmethod
    def from_properties(cls, properties: dict[str, str], where: str) -> PolicyMetadata:
        """The metadata of an exported model.

        :param properties: its ``metadata_props`` (onnxruntime's ``custom_metadata_map``)
        :param where: the model's file, for the messages
        :raises ValueError: a key is missing or unreadable, another format version, or a layout that is not the task's
        """
        values = {}
        for key in (
            "format",
            "config",
            "observation_layout",
            "team_sizes",
            "residual",
            "recurrent",
            "opset",
            "package_version",
        ):
            text = properties.get(METADATA_PREFIX + key)
            if text is None:
                raise ValueError(
                    f"{where} is not a policy exported by sb3-formation: its metadata lack {METADATA_PREFIX + key}"
                )
            try:
                values[key] = json.loads(text)
            except json.JSONDecodeError as error:
                raise ValueError(f"{where}: the metadata {METADATA_PREFIX + key} is not JSON ({error})") from None
        for key, absent in (("safety", None), ("message_size", 0)):  # optional: absent from older files
            text = properties.get(METADATA_PREFIX + key)
            try:
                values[key] = absent if text is None else json.loads(text)
            except json.JSONDecodeError as error:
                raise ValueError(f"{where}: the metadata {METADATA_PREFIX + key} is not JSON ({error})") from None
        size = values["message_size"]
        if not (isinstance(size, int) and not isinstance(size, bool) and size >= 0):
            raise ValueError(f"{where}: the metadata {METADATA_PREFIX}message_size must be an integer >= 0")
        if values["format"] != FORMAT_VERSION:
            raise ValueError(f"{where} has export format {values['format']}; this runtime reads format {FORMAT_VERSION}")
        metadata = cls(
            config=FormationConfig.from_dict(values["config"]),
            team_sizes=tuple(values["team_sizes"]),
            residual=values["residual"],
            recurrent=values["recurrent"],
            safety=values["safety"],
            message_size=values["message_size"],
            opset=int(values["opset"]),
            package_version=str(values["package_version"]),
        )
        if json.loads(metadata.to_properties()[METADATA_PREFIX + "observation_layout"]) != values["observation_layout"]:
            raise ValueError(f"{where}: the observation layout in its metadata is not the layout of its task")
        if metadata.recurrent is not None and metadata.recurrent.get("cell") not in STATE_PARTS:
            raise ValueError(f"{where}: unknown recurrent cell {metadata.recurrent.get('cell')!r}; cells: {list(STATE_PARTS)}")
        return metadata


def _onnxruntime() -> Any:
    """The onnxruntime module, or a one-line error saying how to install it."""
    try:
        import onnxruntime
    except ImportError:
        raise ImportError("running an exported policy needs onnxruntime: pip install 'sb3-formation[runtime]'") from None
    return onnxruntime


def _first_line(error: Exception) -> str:
    """The first line of an error's message (onnx and onnxruntime write several), or its type's name."""
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


def graph_digest(model: Any) -> str:
    """The SHA-256 of an ONNX model's serialised graph (its nodes and weights, not its metadata), as hex.

    :param model: an ``onnx.ModelProto``
    """
    return hashlib.sha256(model.graph.SerializeToString(deterministic=True)).hexdigest()


def check_graph(path: Path) -> None:
    """Refuse an ONNX file that was changed since its export, or that would take more memory than a policy can need,
    before onnxruntime builds it (which folds constants, so a 40000 x 40000 ``ConstantOfShape`` is allocated then): a
    graph whose SHA-256 is not the one its metadata record (:data:`GRAPH_DIGEST_KEY`: flipped weight bytes), a file
    beyond :data:`~sb3_formation.utils.files.MAX_FILE_BYTES`, weights kept in external files, or any tensor (weight,
    input, output, or value whose size shape inference knows before the graph runs) of more than
    :data:`MAX_TENSOR_ELEMENTS` elements. A size computed from the observation's values at run time is not known
    here; onnxruntime's errors at run time are one-line errors (:meth:`OnnxPolicy.agent_step`).

    :raises ValueError: naming the file and what is wrong
    """
    if (size := path.stat().st_size) > MAX_FILE_BYTES:
        raise ValueError(f"{path} holds {size} bytes, beyond the limit of {MAX_FILE_BYTES} bytes for an exported policy")
    try:
        import onnx
    except ImportError:
        raise ImportError("running an exported policy needs onnx: pip install 'sb3-formation[runtime]'") from None
    try:
        model = onnx.load(str(path), load_external_data=False)
        inferred = onnx.shape_inference.infer_shapes(model, data_prop=True)
    except Exception as error:  # onnx raises protobuf's and its own exception types for damaged files
        raise ValueError(f"{path} is not a readable ONNX model: {_first_line(error)}") from None
    properties = {entry.key: entry.value for entry in model.metadata_props}
    recorded = properties.get(GRAPH_DIGEST_KEY)
    if recorded is None:
        PolicyMetadata.from_properties(properties, str(path))  # names a missing key, or an earlier format
        raise ValueError(
            f"{path} is not a policy exported by sb3-formation (format {FORMAT_VERSION}): its metadata lack "
            f"{GRAPH_DIGEST_KEY}; export it again"
        )
    if json.loads(recorded) != graph_digest(model):
        raise ValueError(f"{path} was changed since its export: its graph's SHA-256 is not the one its metadata record")
    graph = inferred.graph
    if any(tensor.data_location == onnx.TensorProto.EXTERNAL for tensor in graph.initializer):
        raise ValueError(f"{path} keeps weights in other files: an exported policy holds all of them itself")
    shapes = {tensor.name: list(tensor.dims) for tensor in graph.initializer}
    for value in (*graph.input, *graph.output, *graph.value_info):
        shapes[value.name] = [dim.dim_value for dim in value.type.tensor_type.shape.dim if dim.HasField("dim_value")]
    for name, dims in shapes.items():
        if math.prod(dims) > MAX_TENSOR_ELEMENTS:
            raise ValueError(
                f"{path}: its tensor {name!r} of shape {dims} has more than {MAX_TENSOR_ELEMENTS} elements, the limit for "
                "an exported policy"
            )


class OnnxPolicy(Policy):
    """An exported policy on the policy seam (:class:`~sb3_formation.controllers.base.Policy`): evaluation,
    rendering and comparison run it as any target (``onnx:path/to/file.onnx`` or the path itself). It never filters its
    actions (:func:`load_onnx_policy` puts a shielded export behind the filter).

    On a robot, :meth:`agent_step` acts for the agents it hosts (their observations, their indices in the team and the
    messages their ring neighbours sent).

    :param path: the ``.onnx`` file ``sb3-formation export`` wrote
    :param threads: onnxruntime's intra-op threads (``None``: its default, one per core)
    :raises FileNotFoundError: there is no file at ``path``
    :raises ValueError: the file is not an ONNX model, or not one exported by sb3-formation
    """

    def __init__(self, path: str | os.PathLike[str], threads: int | None = None) -> None:
        self.source = Path(path)
        if not self.source.is_file():
            raise FileNotFoundError(
                f"no exported policy at {self.source}: write one with `sb3-formation export TARGET --onnx FILE`"
            )
        onnxruntime = _onnxruntime()
        check_graph(self.source)
        options = onnxruntime.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
        try:
            self.session = onnxruntime.InferenceSession(str(self.source), options, providers=["CPUExecutionProvider"])
        except Exception as error:  # onnxruntime raises its own exception types for damaged files
            raise ValueError(f"{self.source} is not a readable ONNX model: {_first_line(error)}") from None
        self.metadata = PolicyMetadata.from_properties(self.session.get_modelmeta().custom_metadata_map, str(self.source))
        inputs, outputs = [node.name for node in self.session.get_inputs()], [node.name for node in self.session.get_outputs()]
        if inputs != self.metadata.input_names or outputs != self.metadata.output_names:
            raise ValueError(
                f"{self.source}: the graph's inputs {inputs} and outputs {outputs} are not those its metadata promise "
                f"({self.metadata.input_names}, {self.metadata.output_names})"
            )
        self.config = self.metadata.config
        self.observation_dim = self.metadata.observation_dim
        self._check_declared_widths()
        spec = self.metadata.residual
        #: a residual policy's controller and scale, which :meth:`agent_step` adds to the graph's correction, else None
        self.residual = None if spec is None else ResidualAdapter(controller_from_spec(spec, self.config), spec["scale"])
        try:
            #: the safety filter's gains of a policy trained behind it (:func:`load_onnx_policy` applies them), else None
            self.safety_gains = None if self.metadata.safety is None else SafetyGains.from_dict(self.metadata.safety)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{self.source}: the safety filter's gains in its metadata are invalid: {error}") from None

    def _check_declared_widths(self) -> None:
        """Refuse a graph whose inputs are not as wide as its metadata say (observation features, state width).

        :raises ValueError: naming the input and both widths
        """
        widths: dict[str, Any] = {OBSERVATION_INPUT: self.observation_dim}
        if self.metadata.recurrent is not None:
            widths |= {f"{part}_in": self.metadata.recurrent.get("hidden") for part in self.metadata.state_parts}
        widths[MESSAGE_INPUT] = 2 * self.metadata.message_size
        for node in self.session.get_inputs():
            if node.shape[-1] != widths[node.name]:
                raise ValueError(
                    f"{self.source}: its graph's input {node.name!r} is {node.shape[-1]} wide, its metadata say "
                    f"{widths[node.name]}"
                )

    @property
    def any_team_size(self) -> bool:
        """Whether it acts in teams of any size (it was trained on several)."""
        return len(self.metadata.team_sizes) > 1

    @property
    def message_size(self) -> int:
        return self.metadata.message_size

    def fit(self, config: FormationConfig) -> OnnxPolicy:
        """The policy acting in envs of ``config``: ``self``, or a copy (same session) whose controller acts there.

        :raises ValueError: :func:`~sb3_formation.controllers.base.check_fit`'s differences
        """
        if config == self.config:
            return self
        check_fit(str(self.source), self.config, config, self.any_team_size)
        fitted = copy.copy(self)
        fitted.config = config
        fitted.residual = None if self.residual is None else self.residual.fit(config)
        return fitted

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """Actions ``(k, 2)`` for the raw observations of any agents, e.g. the one a robot hosts, their next state and
        the messages they send.

        :param observations: ``(k, obs_dim)`` (or one ``(obs_dim,)``) raw observations
        :param agents: ``(k,)`` each row's agent index in its team, or ``(k, 2)`` its place and ring size once agents
            failed (a residual policy's controller needs it)
        :param state: what the previous call returned for these rows (``None`` at the start): a recurrent graph's
            state; for a residual policy the pair (the graph's state, the controller's memory)
        :param episode_start: ``(k,)`` flags: reset these rows' state first
        :param received: ``(k, 2, M)`` (or ``(k, 2 M)``) the messages each row's preceding and succeeding neighbours
            sent at their last step (``None``: zeros, as at an episode's start); policies with messages only
        :param deterministic: must be True: the graph holds the mean action only
        :raises ValueError: observations or messages of the wrong size, a state of the wrong shape, or
            ``deterministic=False``
        """
        if not deterministic:
            raise ValueError(f"{self.source} acts deterministically only (its graph holds the mean action): drop --stochastic")
        rows = np.asarray(observations, dtype=np.float32)
        graph_state, memory = (state, None) if self.residual is None else state_pair(str(self.source), state)
        feeds = {OBSERVATION_INPUT: rows, **self._state_feeds(graph_state, episode_start, len(rows))}
        if self.message_size:
            feeds[MESSAGE_INPUT] = np.zeros((len(rows), 2 * self.message_size), np.float32) if received is None else received
        try:
            first, *outputs = self.session.run(self.metadata.output_names, feeds)
        except Exception as error:  # onnxruntime raises its own exception types (InvalidArgument, Fail, ...)
            raise RuntimeError(f"{self.source}: onnxruntime could not run the graph: {_first_line(error)}") from None
        messages = outputs.pop() if self.message_size else no_messages(len(rows))
        graph_state = tuple(outputs) if outputs else graph_state
        if self.residual is None:
            return AgentStep(first, graph_state, messages)
        actions, memory = self.residual.corrected(rows, first, memory, episode_start, agents)
        return AgentStep(actions, (graph_state, memory), messages)

    def _state_feeds(self, state: Any, episode_start: np.ndarray | None, rows: int) -> dict[str, np.ndarray]:
        """The graph's state inputs: ``state`` (zeros if ``None``) with the rows of ``episode_start`` reset."""
        parts = self.metadata.state_parts
        if not parts:
            return {}
        recurrent = cast("dict[str, Any]", self.metadata.recurrent)  # a recurrent actor's: it has state parts
        shape = (1, rows, recurrent["hidden"])
        arrays = cell_state(str(self.source), state, parts, shape)
        if episode_start is not None:
            keep = 1.0 - np.asarray(episode_start, dtype=np.float32).reshape(1, rows, 1)
            arrays = [array * keep for array in arrays]
        return {f"{part}_in": array for part, array in zip(parts, arrays)}


def load_onnx_policy(path: str | os.PathLike[str], threads: int | None = None) -> TeamPolicy:
    """The policy an exported file holds: an :class:`OnnxPolicy`, behind the safety filter
    (:class:`~sb3_formation.safety.policy.SafePolicy`, with the gains its metadata record) when it was trained behind one.

    :param path: the ``.onnx`` file ``sb3-formation export`` wrote
    :param threads: onnxruntime's intra-op threads (``None``: its default)
    """
    policy = OnnxPolicy(path, threads)
    return policy if policy.safety_gains is None else SafePolicy(policy, policy.safety_gains)
