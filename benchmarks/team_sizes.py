"""Team-size benchmark: how policies fly teams of every size n, on the thesis's evaluation protocol.

For every target (default: the classical controller acting in the chapter-5 bearing task, the shipped
one-policy-for-any-size ``pretrained:mixed-ch5-bearing``, which corrects it, and the shipped ``pretrained:ch5-bearing``,
trained on teams of 6, which refuses the other sizes) and every team size n in ``--sizes`` (default 3 to 10),
it plays ``--episodes`` stage-3 episodes from seed 0 with deterministic actions (thesis 5.4: 200) in teams of n agents
and prints a Markdown table: success with its 95 % Wilson interval; over successful episodes the angle error, bearing
error, agent contacts and steps to the goal; whether the policy was trained on that size; the evaluation's wall time.
A last table gives each target's success minus the first target's at every n.

    python benchmarks/team_sizes.py
    python benchmarks/team_sizes.py --targets pretrained:mixed-ch5-bearing --sizes 3,6,10 --episodes 50
"""

from __future__ import annotations

import argparse
import time

from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.reports import table_number
from sb3_formation.experiment.targets import load_policy


def trained_sizes(policy: object) -> tuple[int, ...] | None:
    """The team sizes a trained policy (or the correction of a residual one) was trained on; ``None`` for a controller."""
    return getattr(getattr(policy, "correction", policy), "team_sizes", None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    targets = "controller:classical,pretrained:mixed-ch5-bearing,pretrained:ch5-bearing"
    parser.add_argument("--targets", default=targets, help="comma-separated")
    parser.add_argument("--recipe", default="ch5-bearing", help="the recipe controller targets act in")
    parser.add_argument("--sizes", default="3,4,5,6,7,8,9,10", help="comma-separated team sizes")
    parser.add_argument("--episodes", type=int, default=200, help="stage-3 episodes per size (thesis 5.4: 200)")
    parser.add_argument("--n-envs", type=int, default=8, help="teams played at once")
    args = parser.parse_args()
    targets, sizes = args.targets.split(","), [int(size) for size in args.sizes.split(",")]
    header = "| target | n | trained on n | success (95 % CI) | angle error (deg) | bearing error | agent contacts | steps "
    header += "| wall (min) |"
    rows, rates = [header, "|---|---:|---|---:|---:|---:|---:|---:|---:|"], {}
    for target in targets:
        policy = load_policy(target, recipe=args.recipe if target.startswith("controller:") else None, device="cpu")
        sizes_trained = trained_sizes(policy)
        for n in sizes:
            started = time.perf_counter()
            try:
                summary = evaluate(
                    policy, episodes=args.episodes, n_envs=args.n_envs, env_overrides={"n_agents": n}, record=0
                ).summary
            except ValueError as error:  # a policy trained on one size refuses the others
                rows.append(f"| {target} | {n} | no | refused: {error} | | | | | |")
                continue
            minutes = (time.perf_counter() - started) / 60
            rates[target, n] = summary["success_rate"]
            low, high = summary["success_rate_ci95"]
            means = {key: value["mean"] for key, value in summary["successful_episodes"].items()}
            seen = "-" if sizes_trained is None else ("yes" if n in sizes_trained else "no")
            rows.append(
                f"| {target} | {n} | {seen} | {summary['success_rate']:.1%} ({low:.1%} - {high:.1%}) | "
                f"{table_number(means['angle_error_deg'])} | {table_number(means['bearing_error'])} | "
                f"{table_number(means['collisions_agent'])} | {table_number(means['length'])} | {minutes:.1f} |"
            )
            print(f"{target} n={n}: {summary['success_rate']:.1%} in {minutes:.1f} min", flush=True)
    print(f"\n{args.episodes} stage-3 episodes per size (seed 0 onwards, deterministic); means over the successful ones\n")
    print("\n".join(rows))
    reference = targets[0]
    print(f"\nSuccess minus {reference}'s, in percentage points\n")
    print("| target | " + " | ".join(f"n={n}" for n in sizes) + " |")
    print("|---|" + "---:|" * len(sizes))
    for target in targets[1:]:
        cells = [f"{100 * (rates[target, n] - rates[reference, n]):+.1f}" if (target, n) in rates else "-" for n in sizes]
        print(f"| {target} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
