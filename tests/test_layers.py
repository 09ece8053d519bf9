"""The package's layers: each imports only from the layers below it, and the environment layer loads no learning stack.

Layers, bottom to top: utils, env, controllers, safety, runtime, ros, sb3, experiment, viz, cli
(docs/contributing.md, "Layers").
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "sb3_formation"
#: Layer of each subpackage or top-level module, bottom (0) to top.
LAYERS = {
    "utils": 0,
    "env": 1,
    "controllers": 2,
    "safety": 3,
    "runtime": 4,
    "ros": 5,
    "sb3": 6,
    "experiment": 7,
    "viz": 8,
    "cli": 9,
}
#: Third-party packages the bottom layers (utils, env, controllers, safety, runtime, ros) must not import: the learning and
#: plotting stacks (the runtime and the ROS 2 nodes run an exported policy with numpy and onnxruntime only).
HEAVY = {"torch", "stable_baselines3", "matplotlib", "tensorboard", "ray", "tqdm", "imageio_ffmpeg"}
LIGHT_LAYERS = {"utils", "env", "controllers", "safety", "runtime", "ros"}


def layer(relative: Path) -> str:
    """The layer of a module, from its path inside the package (``env/world.py`` -> ``env``)."""
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def imported_modules(source: str, relative: Path) -> list[str]:
    """Every module a source imports, at any depth (also inside functions), relative imports made absolute."""
    package = ["sb3_formation", *relative.parent.parts]
    modules = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, node.module] if node.module else base)
            modules += [module] + [f"{module}.{alias.name}" for alias in node.names] if node.level else [module]
    return modules


def violations(sources: dict[Path, str]) -> list[str]:
    """The import-rule violations of the package's modules (path inside the package -> source)."""
    found = []
    for relative, source in sorted(sources.items()):
        own = layer(relative)
        if own not in LAYERS:  # the package's __init__: lazy re-exports by name only
            continue
        for module in imported_modules(source, relative):
            parts = module.split(".")
            if parts[0] == "sb3_formation" and len(parts) > 1 and LAYERS.get(parts[1], -1) > LAYERS[own]:
                found.append(f"{relative}: layer {own!r} imports {module} from the higher layer {parts[1]!r}")
            if own in LIGHT_LAYERS and parts[0] in HEAVY:
                found.append(f"{relative}: layer {own!r} imports {parts[0]}")
    return found


def package_sources() -> dict[Path, str]:
    return {path.relative_to(PACKAGE): path.read_text() for path in PACKAGE.rglob("*.py")}


def test_every_module_belongs_to_a_layer() -> None:
    outside = [str(path) for path in package_sources() if layer(path) not in LAYERS and path != Path("__init__.py")]
    assert not outside, f"modules in no layer: {outside}"


def test_each_layer_imports_only_from_the_layers_below() -> None:
    assert violations(package_sources()) == []


@pytest.mark.parametrize(
    ("module", "added", "expected"),
    [
        ("env/world.py", "import torch\n", "env/world.py: layer 'env' imports torch"),
        ("env/rendering.py", "from matplotlib import pyplot\n", "env/rendering.py: layer 'env' imports matplotlib"),
        (
            "env/formation_env.py",
            "def late():\n    from sb3_formation.experiment.training import train\n",
            "env/formation_env.py: layer 'env' imports sb3_formation.experiment.training from the higher layer 'experiment'",
        ),
        (
            "sb3/vec_env.py",
            "from ..viz import plots\n",
            "sb3/vec_env.py: layer 'sb3' imports sb3_formation.viz from the higher layer 'viz'",
        ),
        (
            "controllers/random.py",
            "import stable_baselines3\n",
            "controllers/random.py: layer 'controllers' imports stable_baselines3",
        ),
        ("env/engine.py", "import torch as th\n", "env/engine.py: layer 'env' imports torch"),
        (
            "env/blocks.py",
            "from sb3_formation.sb3.vec_env import FormationVecEnv\n",
            "env/blocks.py: layer 'env' imports sb3_formation.sb3.vec_env from the higher layer 'sb3'",
        ),
        (
            "runtime/onnx_policy.py",
            "import torch\n",
            "runtime/onnx_policy.py: layer 'runtime' imports torch",
        ),
        (
            "runtime/onnx_policy.py",
            "from sb3_formation.sb3.trained import TrainedPolicy\n",
            "runtime/onnx_policy.py: layer 'runtime' imports sb3_formation.sb3.trained from the higher layer 'sb3'",
        ),
        (
            "ros/observer.py",
            "from sb3_formation.sb3.vec_env import FormationVecEnv\n",
            "ros/observer.py: layer 'ros' imports sb3_formation.sb3.vec_env from the higher layer 'sb3'",
        ),
        (
            "utils/checks.py",
            "from sb3_formation.env.config import FormationConfig\n",
            "utils/checks.py: layer 'utils' imports sb3_formation.env.config from the higher layer 'env'",
        ),
    ],
)
def test_the_rule_catches_a_forbidden_import(module: str, added: str, expected: str) -> None:
    """The check is not vacuous: one forbidden import added to a copy of the sources is reported."""
    sources = package_sources()
    sources[Path(module)] = sources[Path(module)] + "\n" + added
    assert expected in violations(sources)


@pytest.mark.parametrize(
    "module",
    [
        "sb3_formation",
        "sb3_formation.env",
        "sb3_formation.controllers",
        "sb3_formation.safety",
        "sb3_formation.runtime",
        "sb3_formation.ros.scans",
        "sb3_formation.ros.observer",
    ],
)
def test_importing_the_light_layers_loads_no_learning_stack(module: str) -> None:
    """Measured in a fresh interpreter: importing the env, the runtime (or the package's top level) leaves torch and SB3
    unloaded."""
    code = f"import sys, {module}; print(sorted(m for m in {sorted(HEAVY)!r} if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]"


def test_public_names_stay_importable_lazily() -> None:
    code = (
        "import sys, sb3_formation\n"
        "assert 'torch' not in sys.modules\n"
        "from sb3_formation import FormationConfig, FormationEnv, Scenario, TASKS, REWARD_TERMS, TeamState\n"
        "assert 'torch' not in sys.modules\n"
        "from sb3_formation import FormationPolicy, FormationVecEnv, ScaleNormalizeVecEnv, make_formation_vec_env\n"
        "from sb3_formation import load_policy, load_recipe\n"
        "assert 'torch' in sys.modules\n"
        "assert set(sb3_formation.__all__) <= set(dir(sb3_formation))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
