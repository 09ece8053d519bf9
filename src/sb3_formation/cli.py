"""The ``sb3-formation`` command line: a thin layer over functions a notebook can call with the same names."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from PIL import Image

from .config import PRESETS, FormationConfig
from .env import FormationEnv
from .rollout import random_policy, run_episode


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(prog="sb3-formation", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    rollout = commands.add_parser(
        "rollout",
        help="play episodes with a random policy, print per-episode metrics and save the final frame",
        description="Play episodes of the formation env with uniformly random actions (a baseline and a smoke test).",
    )
    rollout.add_argument(
        "--preset", choices=sorted(PRESETS), default="ch5-bearing", help="thesis set-up (default: %(default)s)"
    )
    rollout.add_argument("--agents", type=int, default=None, help="team size n >= 3 (default: the preset's)")
    rollout.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default: %(default)s)")
    rollout.add_argument("--episodes", type=_positive_int, default=2, help="number of episodes (default: %(default)s)")
    rollout.add_argument(
        "--max-steps", type=_positive_int, default=None, help="episode length T_s in steps (default: the preset's 2500)"
    )
    rollout.add_argument("--seed", type=int, default=0, help="seed of the first episode; episode k uses seed + k")
    rollout.add_argument("--out", type=Path, default=Path("runs/rollout_final_frame.png"), help="PNG of the final frame")
    rollout.add_argument("--json", action="store_true", help="print the summaries as JSON lines")
    return parser


def rollout_command(args: argparse.Namespace) -> int:
    """``sb3-formation rollout``: random-policy episodes with per-episode metrics and a PNG of the final frame."""
    overrides = {"stage": args.stage}
    if args.agents is not None:
        overrides["n_agents"] = args.agents
    if args.max_steps is not None:
        overrides["max_steps"] = args.max_steps
    config = FormationConfig.preset(args.preset, **overrides)
    env = FormationEnv(config, render_mode="rgb_array")
    policy = random_policy(env, seed=args.seed)
    print(f"{args.preset}: n={config.n_agents}, stage {config.stage}, T_s={config.max_steps}, random policy")
    for episode in range(args.episodes):
        summary = run_episode(env, policy, seed=args.seed + episode)
        if args.json:
            print(json.dumps({"episode": episode, **summary.as_dict()}))
        else:
            print(
                f"episode {episode}: steps={summary.steps} success={summary.success} "
                f"return={summary.mean_agent_return:.2f} angle_error={summary.angle_error_deg:.1f} deg "
                f"bearing_error={summary.bearing_error:.3f} distance_error={summary.neighbour_distance_error:.3f} m "
                f"goal_distance={summary.final_goal_distance:.2f} m "
                f"collisions obstacle/agent={summary.collisions_obstacle}/{summary.collisions_agent}"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(env.render()).save(args.out)
    print(f"final frame saved to {args.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-formation`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return {"rollout": rollout_command}[args.command](args)
    except ValueError as error:  # configuration errors name the field and the allowed range
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
