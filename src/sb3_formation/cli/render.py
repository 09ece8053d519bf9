"""``sb3-formation render``: videos of evaluation episodes."""

from __future__ import annotations

import argparse

from sb3_formation.cli.common import (
    RECIPE_HELP,
    TARGET_HELP,
    add_disturbances_option,
    add_recipe_option,
    add_scenes_option,
    add_trust_pickle_option,
    agents_count,
    disturbances_label,
    episodes_count,
    fps_count,
    model_trust,
    scene_overrides,
    steps_count,
)
from sb3_formation.env.disturbances import load_disturbances
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path, seed_value


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``render`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "render",
        help="write an MP4 or GIF of evaluation episodes",
        description="Play evaluation episodes with a trained policy and write them as a video, with the step, "
        "success and current errors drawn on each frame. The format follows --out: .mp4 or .gif.",
    )
    parser.add_argument("target", help=TARGET_HELP)
    add_recipe_option(parser, RECIPE_HELP)
    parser.add_argument("--episodes", type=episodes_count, default=1, help="episodes (default 1)")
    parser.add_argument("--out", type=output_path, help="video file, .mp4 or .gif (default: <run>/eval/episodes.mp4)")
    parser.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default 3)")
    parser.add_argument("--seed", type=seed_value, default=0, help="episode k plays the scenario of seed + k (default 0)")
    parser.add_argument("--fps", type=fps_count, default=20, help="frames per second (default 20)")
    parser.add_argument("--frame-every", type=steps_count, default=1, help="keep every k-th step as a frame")
    parser.add_argument("--max-steps", type=steps_count, help="cut episodes at this many steps (default: the model's)")
    parser.add_argument(
        "--agents", type=agents_count, help="team size (default: the model's; another only for one trained on several)"
    )
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    add_scenes_option(parser)
    add_disturbances_option(parser)
    add_trust_pickle_option(parser)
    parser.set_defaults(run=run)


def starting(args: argparse.Namespace) -> str:
    """The line ``render`` starts with."""
    return f"rendering {args.episodes} episode(s) of {args.target} (Ctrl-C stops it)"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation render``: a video of evaluation episodes."""
    from sb3_formation.viz.video import render_episodes  # imported only by the command that uses it

    target = Target.parse(args.target, args.recipe)
    with model_trust(args):
        policy = target.load(device=args.device)
    out = args.out or target.evaluation_folder(args.scenes or policy.config.scenes, disturbances_label(args)) / "episodes.mp4"
    frames = render_episodes(
        policy,
        out,
        episodes=args.episodes,
        stage=args.stage,
        seed=args.seed,
        deterministic=not args.stochastic,
        fps=args.fps,
        frame_every=args.frame_every,
        env_overrides={
            **scene_overrides(args),
            **({} if args.disturbances is None else {"disturbances": load_disturbances(args.disturbances)}),
            **({} if args.max_steps is None else {"max_steps": args.max_steps}),
        },
        progress_bar=True,
    )
    print(f"{frames} frames written to {out}")
    return 0
