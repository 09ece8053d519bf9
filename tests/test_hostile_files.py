"""Files someone hands a user that declare more than they hold: a model file that inflates to gigabytes, a normaliser
that declares 10^10 floats, an ONNX graph that builds a 40000 x 40000 tensor or declares a 2^31-wide state. Each is
refused with one line before anything large is allocated (measured with tracemalloc, which sees Python's and numpy's
allocations)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sb3_formation.cli import main
from sb3_formation.experiment.evaluation import MAX_RECORDED_EPISODES
from sb3_formation.experiment.export import ONNX_FILE
from sb3_formation.experiment.pretrained import PRETRAINED_DIR
from sb3_formation.runtime.onnx_policy import MAX_TENSOR_ELEMENTS, METADATA_PREFIX, OnnxPolicy, PolicyMetadata, graph_digest
from sb3_formation.utils.files import MAX_FILE_BYTES
from sb3_formation.utils.yaml_files import MAX_YAML_NODES

#: Most bytes (Python's and numpy's) that refusing a bomb may allocate.
REFUSAL_BYTES = 64 << 20


def refused_with_one_line(capsys: pytest.CaptureFixture[str], arguments: list[str]) -> str:
    """Run the CLI under tracemalloc: it must fail with exit code 2 and one line, having allocated little.

    :return: the line
    """
    tracemalloc.start()
    try:
        code = main(arguments)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    error = capsys.readouterr().err
    assert code == 2 and error.count("\n") == 1 and "Traceback" not in error, error
    assert peak < REFUSAL_BYTES, f"{peak} bytes allocated to refuse it"
    return error


def shipped_copy(tmp_path: Path, name: str = "ch5-bearing") -> Path:
    """A copy of a shipped policy's folder, to spoil."""
    return Path(shutil.copytree(PRETRAINED_DIR / name, tmp_path / name))


def inflating_entry(archive: zipfile.ZipFile, name: str, size: int) -> None:
    """Write an entry of ``size`` zero bytes (a few MB once deflated)."""
    chunk = bytes(1 << 24)
    with archive.open(name, "w", force_zip64=True) as stream:
        for _ in range(-(-size // len(chunk))):
            stream.write(chunk)


def evaluate(target: Path) -> list[str]:
    return ["evaluate", str(target), "--episodes", "1", "--out", str(target.parent / "eval"), "--no-progress"]


@pytest.mark.parametrize("entry", ["data", "policy.pth"])
def test_a_model_file_that_inflates_beyond_the_limit_is_refused(
    tmp_path: Path, entry: str, capsys: pytest.CaptureFixture[str]
) -> None:
    source, bomb = PRETRAINED_DIR / "ch5-bearing" / "final_model.zip", shipped_copy(tmp_path) / "final_model.zip"
    bomb.unlink()
    with zipfile.ZipFile(source) as original, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as out:
        for info in original.infolist():
            if info.filename != entry:
                out.writestr(info, original.read(info))
        inflating_entry(out, entry, MAX_FILE_BYTES + 1)
    assert bomb.stat().st_size < 10 << 20
    error = refused_with_one_line(capsys, evaluate(bomb.parent))
    assert f"its entry '{entry}' inflates to" in error and f"limit of {MAX_FILE_BYTES} bytes" in error


def npy_header(shape: tuple[int, ...]) -> bytes:
    """An ``.npy`` file's header declaring float64s of ``shape``, and 8 bytes of data."""
    import io

    stream = io.BytesIO()
    np.lib.format.write_array_header_1_0(stream, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return stream.getvalue() + bytes(8)


@pytest.mark.parametrize(
    "spoil",
    [
        lambda archive: archive.writestr("mean.npy", npy_header((10**10,))),
        lambda archive: inflating_entry(archive, "mean.npy", MAX_FILE_BYTES + 1),
    ],
    ids=["declares 10^10 floats", "inflates beyond the limit"],
)
def test_a_normaliser_that_declares_more_than_it_holds_is_refused(
    tmp_path: Path, spoil: Callable[[zipfile.ZipFile], None], capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shipped_copy(tmp_path)
    normaliser = folder / "final_normalizer.npz"
    with np.load(normaliser) as arrays:
        kept = {key: arrays[key] for key in arrays.files if key != "mean"}
    normaliser.unlink()
    with zipfile.ZipFile(normaliser, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for key, value in kept.items():
            with archive.open(f"{key}.npy", "w") as stream:
                np.lib.format.write_array(stream, value)
        spoil(archive)
    assert normaliser.stat().st_size < 10 << 20
    error = refused_with_one_line(capsys, evaluate(folder))
    assert f"{normaliser} is not a normaliser file: its " in error and "empty or damaged" not in error
    declared = "its array 'mean.npy' declares 80000000000 bytes in an entry of"  # 10^10 float64s
    assert declared in error or "its entry 'mean.npy' inflates to" in error


def spoiled_graph(tmp_path: Path, spoil: Callable[[Any], None]) -> Path:
    """The shipped ``ch5-bearing`` graph (residual: its output is ``correction``), spoilt by ``spoil(model)``."""
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE))
    spoil(model)
    set_metadata(model, "graph_sha256", json.dumps(graph_digest(model)))  # as a spoiler who knows the format would
    path = tmp_path / "spoilt.onnx"
    onnx.save(model, str(path))
    return path


def builds_a_huge_constant(model: Any) -> None:
    """correction = (the graph's correction) + sum(ConstantOfShape([40000, 40000])): 6.4 GB once folded."""
    from onnx import helper, numpy_helper

    graph = model.graph
    for node in graph.node:
        node.output[:] = ["unspoilt" if name == "correction" else name for name in node.output]
    graph.node.extend(
        [
            helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array([40000, 40000]))),
            helper.make_node("ConstantOfShape", ["shape"], ["huge"], value=numpy_helper.from_array(np.zeros(1, np.float32))),
            helper.make_node("ReduceSum", ["huge"], ["total"], keepdims=0),
            helper.make_node("Add", ["unspoilt", "total"], ["correction"]),
        ]
    )


def declares_a_huge_state(model: Any) -> None:
    """A GRU's state of width 2^31 in the metadata and the graph (the state passes through)."""
    from onnx import TensorProto, helper

    model.graph.input.append(helper.make_tensor_value_info("hidden_in", TensorProto.FLOAT, [1, "batch", 2**31]))
    model.graph.output.append(helper.make_tensor_value_info("hidden_out", TensorProto.FLOAT, [1, "batch", 2**31]))
    model.graph.node.append(helper.make_node("Identity", ["hidden_in"], ["hidden_out"]))
    set_metadata(model, "recurrent", json.dumps({"cell": "gru", "hidden": 2**31}))


def set_metadata(model: Any, key: str, value: str) -> None:
    for entry in model.metadata_props:
        if entry.key == METADATA_PREFIX + key:
            entry.value = value


def narrows_the_task(model: Any) -> None:
    """The metadata name a task with one lidar ray fewer (two features fewer: 209) than the graph reads (211)."""
    metadata = PolicyMetadata.from_properties({entry.key: entry.value for entry in model.metadata_props}, "the graph")
    config = dataclasses.replace(metadata.config, lidar_rays=metadata.config.lidar_rays - 1)
    for key, value in dataclasses.replace(metadata, config=config).to_properties().items():
        set_metadata(model, key.removeprefix(METADATA_PREFIX), value)


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (builds_a_huge_constant, f"its tensor 'huge' of shape [40000, 40000] has more than {MAX_TENSOR_ELEMENTS} elements"),
        (declares_a_huge_state, f"its tensor 'hidden_in' of shape [1, 2147483648] has more than {MAX_TENSOR_ELEMENTS}"),
        (narrows_the_task, "its graph's input 'observation' is 211 wide, its metadata say 209"),
    ],
    ids=["ConstantOfShape 40000 x 40000", "state of 2^31", "input wider than its metadata say"],
)
def test_an_onnx_graph_that_declares_more_than_a_policy_needs_is_refused(
    tmp_path: Path, spoil: Callable[[Any], None], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    error = refused_with_one_line(
        capsys, ["evaluate", str(spoiled_graph(tmp_path, spoil)), "--episodes", "1", "--no-progress"]
    )
    assert message in error


def test_onnxruntime_errors_at_run_time_are_one_line(tmp_path: Path) -> None:
    """A graph that fails only when it runs (a Reshape to a size its input does not have)."""

    def reshapes_wrongly(model: Any) -> None:
        from onnx import helper, numpy_helper

        graph = model.graph
        for node in graph.node:
            node.output[:] = ["unspoilt" if name == "correction" else name for name in node.output]
        graph.node.extend(
            [
                helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array([-1, 3]))),
                helper.make_node("Reshape", ["unspoilt", "shape"], ["reshaped"]),
                helper.make_node("Reshape", ["reshaped", "shape_back"], ["correction"]),
                helper.make_node("Constant", [], ["shape_back"], value=numpy_helper.from_array(np.array([-1, 2]))),
            ]
        )

    policy = OnnxPolicy(spoiled_graph(tmp_path, reshapes_wrongly))
    with pytest.raises(RuntimeError, match=r"spoilt\.onnx: onnxruntime could not run the graph: ") as error:
        policy.agent_step(np.zeros((1, policy.observation_dim), np.float32), np.zeros(1, int))
    assert "\n" not in str(error.value)


def laughs(levels: int = 10) -> str:
    """A YAML flow list of anchors nested ``levels`` deep, each alias ten times the one before: 10^levels items once
    expanded, in a few hundred bytes."""
    items = ["&l0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    items += [f"&l{level} [{', '.join([f'*l{level - 1}'] * 10)}]" for level in range(1, levels)]
    return f"[{', '.join(items)}]"


@pytest.mark.parametrize("field", ["policy:\n  net_arch:\n    pi", "env:\n  v_max"], ids=["a section", "a numeric field"])
def test_a_recipe_of_nested_yaml_anchors_is_refused_before_it_expands(
    tmp_path: Path, field: str, capsys: pytest.CaptureFixture[str]
) -> None:
    bomb = tmp_path / "laughs.yaml"
    bomb.write_text(f"base: ch5-bearing\n{field}: {laughs()}\n")
    assert bomb.stat().st_size < 1024
    error = refused_with_one_line(capsys, ["train", "--recipe", str(bomb), "--logdir", str(tmp_path / "runs")])
    assert f"{bomb} is not valid YAML: its aliases expand it to more than {MAX_YAML_NODES} nodes" in error
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("options", "recipe", "message"),
    [
        (
            ["--env", "lidar_rays=100000000"],
            None,
            "FormationConfig.lidar_rays=100000000 is invalid: it must be an integer >= 1 and <= 3600",
        ),
        (["--n-envs", "100000000"], None, "n_envs must be at most 1024 (teams played at once), got 100000000"),
        (
            [],
            {"ppo": {"n_steps": 100_000_000}},
            "would hold 6853.0 GiB of rollout, beyond the limit of 4 GiB",
        ),  # 1e8 x 84 x (211 + 8) x 4 B
        (["--agents", "1000"], None, "FormationConfig.n_agents=1000 is invalid: it must be an integer >= 3 and <= 64"),
    ],
    ids=["lidar rays", "teams", "rollout", "agents"],
)
def test_sizes_that_would_exhaust_memory_are_refused_before_anything_is_allocated(
    tmp_path: Path, options: list[str], recipe: dict[str, Any] | None, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    if recipe is not None:
        (tmp_path / "big.yaml").write_text(json.dumps({"base": "ch5-bearing", **recipe}))
        options = ["--recipe", str(tmp_path / "big.yaml")]
    assert message in refused_with_one_line(capsys, ["train", *options, "--logdir", str(tmp_path / "runs")])
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("count", ["2000", "-1"])
def test_recording_more_episodes_than_memory_allows_is_refused(
    tmp_path: Path, count: str, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["evaluate", "controller:classical", "--episodes", "2000", "--trajectories", count]
    error = refused_with_one_line(capsys, [*arguments, "--out", str(tmp_path / "eval"), "--no-progress"])
    assert f"record (--trajectories) must be in [0, {MAX_RECORDED_EPISODES}], got {count}" in error
    assert not (tmp_path / "eval").exists()


def test_an_onnx_file_with_flipped_weight_bytes_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """200 bytes of the weights flipped in the file itself: the graph's SHA-256 is not the recorded one."""
    onnx = pytest.importorskip("onnx")
    source = PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE
    data = bytearray(source.read_bytes())
    weights = max(onnx.load(str(source)).graph.initializer, key=lambda tensor: len(tensor.raw_data)).raw_data
    start = bytes(data).index(weights[:64]) + 1000  # inside the largest weight matrix
    data[start : start + 200] = bytes(byte ^ 0x55 for byte in data[start : start + 200])
    flipped = tmp_path / "flipped.onnx"
    flipped.write_bytes(bytes(data))
    error = refused_with_one_line(capsys, ["evaluate", str(flipped), "--episodes", "1", "--no-progress"])
    assert f"{flipped} was changed since its export: its graph's SHA-256 is not the one its metadata record" in error


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"success_rate": "96%"}, "success_rate must be a number in [0, 1]"),
        ({"success_rate_ci95": [0.1]}, "success_rate_ci95 must be two numbers"),
        ({"episodes": "200"}, "episodes must be an integer >= 0"),
        ({"successful_episodes": {"length": {"mean": "long", "std": 0}}}, "successful_episodes must be a mapping"),
    ],
)
def test_a_damaged_summary_is_named_in_one_line(
    change: dict[str, Any], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An edited ``summary.json`` read by ``plot`` names the file and the entry (not "Unknown format code '%'")."""
    folder = tmp_path / "eval"
    assert (
        main(["evaluate", "controller:classical", "--episodes", "2", "--n-envs", "2", "--out", str(folder), "--no-progress"])
        == 0
    )
    summary = json.loads((folder / "summary.json").read_text())
    (folder / "summary.json").write_text(json.dumps(summary | change))
    capsys.readouterr()
    assert main(["plot", "bars", str(folder), "--out", str(tmp_path / "bars.png")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and f"{folder / 'summary.json'} is damaged" in error and message in error, error
    assert not (tmp_path / "bars.png").exists()
