"""``sb3-formation ros sim|agents``: the ROS 2 nodes (``docs/deployment.md``), started with a policy named as every command
names one; the nodes run in ``python -m sb3_formation.ros`` (:mod:`sb3_formation.ros.launch`), which imports no torch."""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from sb3_formation.cli.common import TARGET_HELP
from sb3_formation.experiment.pretrained import ONNX_FILE, pretrained_folder
from sb3_formation.experiment.targets import Target
from sb3_formation.ros.launch import add_arguments


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``ros`` subcommand (with ``sim`` and ``agents``) to ``commands``."""
    parser = commands.add_parser(
        "ros",
        help="policies on robots over ROS 2: the simulator node and the agent nodes (needs the ros extra)",
        description="Run the simulator as a ROS 2 node, or a team's agent nodes (docs/deployment.md).",
    )
    add_arguments(parser.add_subparsers(dest="ros_command", required=True), f"the policy: {TARGET_HELP}; exported or shipped")
    parser.set_defaults(run=run)


def exported_file(target: Target) -> str:
    """The ``.onnx`` file of a target: a shipped policy's, or the exported file it names.

    :raises ValueError: a target that is neither (export it first)
    """
    if target.kind == "pretrained":
        return str(pretrained_folder(target.name) / ONNX_FILE)
    if target.kind == "onnx":
        return str(target.path)
    raise ValueError(
        f"the ROS 2 nodes run an exported policy: export {target} first (sb3-formation export {target} --onnx FILE)"
    )


def run(args: argparse.Namespace) -> int:
    """Hand over to ``python -m sb3_formation.ros`` with the target's ``.onnx`` file (this process is replaced)."""
    argv = shlex.split(args.command_line)
    argv = argv[argv.index("ros") + 1 :]
    argv[argv.index(args.model)] = exported_file(Target.parse(args.model))
    os.execv(sys.executable, [sys.executable, "-m", "sb3_formation.ros", *argv])
    return 0  # pragma: no cover - execv does not return
