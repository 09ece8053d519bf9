"""``sb3-formation rollout``: episodes of any policy with per-episode metrics."""

from __future__ import annotations

import argparse
import json

from PIL import Image

from sb3_formation.cli.common import (
    TARGET_HELP,
    add_recipe_option,
    add_trust_pickle_option,
    agents_count,
    episodes_count,
    model_trust,
    steps_count,
)
from sb3_formation.env.rendering import render_frame
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.recipes import DEFAULT_RECIPE
from sb3_formation.experiment.rollouts import PlayJob, play_episodes, seed_policy
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path, seed_value
from sb3_formation.utils.files import atomic_path


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``rollout`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "rollout",
        help="play episodes (random actions by default), print per-episode metrics and save the final frame",
        description="Play episodes of the formation env with a policy (by default controller:random, uniformly random "
        "actions: a baseline and a smoke test), print each episode's metrics and save the last frame as a PNG.",
    )
    parser.add_argument("target", nargs="?", default="controller:random", help=TARGET_HELP + " (default: %(default)s)")
    add_recipe_option(parser, f"recipe of a controller: target (default: {DEFAULT_RECIPE})")
    parser.add_argument("--agents", type=agents_count, default=None, help="team size n >= 3 (default: the recipe's)")
    parser.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default: %(default)s)")
    parser.add_argument("--episodes", type=episodes_count, default=2, help="number of episodes (default: %(default)s)")
    parser.add_argument(
        "--max-steps", type=steps_count, default=None, help="episode length T_s in steps (default: the recipe's 2500)"
    )
    parser.add_argument("--seed", type=seed_value, default=0, help="seed of the first episode; episode k uses seed + k")
    parser.add_argument(
        "--out", type=output_path, default=output_path("runs/rollout_final_frame.png"), help="PNG of the final frame"
    )
    parser.add_argument("--json", action="store_true", help="print the summaries as JSON lines")
    parser.add_argument("--stochastic", action="store_true", help="sample a trained policy's actions")
    add_trust_pickle_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation rollout``: episodes of any policy with per-episode metrics and a PNG of the final frame."""
    with model_trust(args):
        policy = Target.parse(args.target, args.recipe).load(device="cpu")
    overrides = {"stage": args.stage}
    if args.agents is not None:
        overrides["n_agents"] = args.agents
    if args.max_steps is not None:
        overrides["max_steps"] = args.max_steps
    config = policy.config.replace(**overrides)
    job = PlayJob(policy.fit(config), config, args.seed, list(range(args.episodes)), 1, not args.stochastic, 0)
    last: list[TeamState] = []

    def keep(state: TeamState, episode: int) -> None:
        last[:] = [state]

    seed_policy(job.policy, args.seed)
    rows, _ = play_episodes(job, on_step=keep)
    print(f"{args.target}: n={config.n_agents}, stage {config.stage}, T_s={config.max_steps}")
    for summary in rows:
        if args.json:
            print(json.dumps({key: value for key, value in summary.items() if not key.startswith("reward_")}))
        else:
            print(
                f"episode {summary['episode']}: steps={summary['length']} success={summary['success']} "
                f"return={summary['return']:.2f} angle_error={summary['angle_error_deg']:.1f} deg "
                f"bearing_error={summary['bearing_error']:.3f} distance_error={summary['neighbour_distance_error']:.3f} m "
                f"goal_distance={summary['final_goal_distance']:.2f} m "
                f"collisions obstacle/agent={summary['collisions_obstacle']}/{summary['collisions_agent']}"
            )
    with atomic_path(args.out) as temporary:
        Image.fromarray(render_frame(last[0], config)).save(temporary, format="PNG")
    print(f"final frame saved to {args.out}")
    return 0
