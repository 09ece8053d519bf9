"""``sb3-formation export``: write a trained policy as an ONNX model that runs without torch (``docs/export.md``)."""

from __future__ import annotations

import argparse

from sb3_formation.cli.common import TARGET_HELP, add_trust_pickle_option, model_trust
from sb3_formation.experiment.targets import Target
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.sb3.onnx_export import DEFAULT_OPSET, SUPPORTED_OPSETS, export_onnx
from sb3_formation.utils.arguments import output_path


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "export",
        help="export a trained policy to ONNX (run it with onnxruntime, without torch)",
        description="Write a trained policy's actor as an ONNX model: raw observations of one agent or a batch in, the "
        "clipped action out, the normaliser folded in, a recurrent state as input and output, the task and "
        "observation layout in its metadata. A residual policy's graph is the correction; the runtime "
        "(sb3_formation.runtime.OnnxPolicy) adds the controller's action. Evaluate the file as any target: "
        "sb3-formation evaluate out.onnx",
    )
    parser.add_argument("target", help=TARGET_HELP)
    parser.add_argument("--onnx", type=output_path, required=True, metavar="FILE", help="the .onnx file to write")
    parser.add_argument(
        "--opset",
        type=int,
        default=DEFAULT_OPSET,
        help=f"ONNX opset, {SUPPORTED_OPSETS[0]}-{SUPPORTED_OPSETS[-1]} (default {DEFAULT_OPSET})",
    )
    add_trust_pickle_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation export``: the target's policy written to ``--onnx``, then read back by the runtime."""
    with model_trust(args):
        policy = Target.parse(args.target).load(device="cpu")
    path = export_onnx(policy, args.onnx, opset=args.opset)
    metadata = OnnxPolicy(path).metadata
    print(f"{args.target} exported to {path} (opset {metadata.opset})")
    print(f"  inputs {metadata.input_names}, outputs {metadata.output_names}")
    return 0
