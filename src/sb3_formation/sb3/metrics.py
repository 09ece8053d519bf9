"""The episode metrics' catalogue: for every key of an episode summary, its table heading, chart title, axis label and
TensorBoard tag (one list for TensorBoard, evaluation summaries, tables and figures).

The summaries themselves are the environment layer's (:func:`~sb3_formation.env.episodes.episode_summary`); how they
are shown lives here, above it, beside the logger that writes the tags.
"""

from __future__ import annotations

from dataclasses import dataclass

from sb3_formation.safety.policy import SAFETY_METRIC_KEYS


@dataclass(frozen=True)
class Metric:
    """One per-episode metric.

    :param label: table heading, with the unit
    :param title: short title of its chart
    :param axis: axis label of its chart, with the unit
    :param tensorboard: its TensorBoard tag during training (``None``: evaluation only)
    :param in_table: a column of comparison tables
    """

    label: str
    title: str
    axis: str
    tensorboard: str | None
    in_table: bool = True


#: Every per-episode metric, by its key in episode summaries (``formation_episode`` infos, ``episodes.csv``, the means
#: of ``summary.json``). Errors are means over the episode's steps of the means over agents; collisions are totals.
EPISODE_METRICS: dict[str, Metric] = {
    "angle_error_deg": Metric("angle error (deg)", "angle error", "angle error (deg)", "formation/angle_error_deg"),
    "bearing_error": Metric("bearing error", "bearing error", "bearing error", "formation/bearing_error"),
    "neighbour_distance_error": Metric(
        "distance error (m)", "neighbour-distance error", "distance error (m)", "formation/neighbour_distance_error"
    ),
    "length": Metric("steps", "episode length", "steps", "episode/length"),
    "collisions_obstacle": Metric(
        "obstacle collisions", "obstacle collisions", "collisions per episode", "episode/collisions_obstacle"
    ),
    "collisions_agent": Metric("agent collisions", "agent collisions", "collisions per episode", "episode/collisions_agent"),
    "comm_exceeded_fraction": Metric(
        "beyond communication range", "beyond communication range", "fraction of steps", None, in_table=False
    ),
}
#: What only some worlds' episodes have, summarised where the episodes have it (the evaluation files of a still world
#: whose agents never fail are as they were before obstacles moved and agents failed): of the obstacle collisions,
#: those where a moving obstacle ran into an agent that was braking, standing or moving away
#: (:class:`~sb3_formation.env.engine.ContactColumn`; episodes with moving obstacles), and the agents that failed
#: (episodes of a task whose agents may fail).
WORLD_METRICS: dict[str, Metric] = {
    "collisions_rammed": Metric(
        "rammed by movers", "obstacle collisions a mover ran into", "collisions per episode", "episode/collisions_rammed"
    ),
    "failed_agents": Metric("failed agents", "agents that failed", "agents per episode", "episode/failed_agents"),
}
#: TensorBoard tag of the rolling success rate during training.
SUCCESS_RATE_TAG = "episode/success_rate"
#: What the safety filter did in an episode (:class:`~sb3_formation.safety.policy.SafePolicy`): only episodes of a
#: filtered policy have them. The changed share is over agent-steps, the mean change over the changed ones (fraction of
#: F_max), infeasible steps are agent-steps, and the separation is the smallest gap (m) the agents measured.
SAFETY_METRICS: dict[str, Metric] = dict(
    zip(
        SAFETY_METRIC_KEYS,
        (
            Metric("filter changed", "actions the filter changed", "share of agent-steps", "safety/changed_fraction"),
            Metric("mean change", "size of the filter's change", "fraction of F_max", "safety/change_mean"),
            Metric("infeasible steps", "infeasible agent-steps", "agent-steps per episode", "safety/infeasible_steps"),
            Metric("min separation (m)", "smallest separation", "gap (m)", "safety/min_separation"),
        ),
    )
)
