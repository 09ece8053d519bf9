"""Names the training metrics must have, written down once for the tests that check them (not read from the package)."""

from sb3_formation import REWARD_TERMS

#: Per team-episode scalars FormationMetricsCallback must log (besides curriculum/stage).
EPISODE_SCALARS = [
    "formation/angle_error_deg",
    "formation/bearing_error",
    "formation/neighbour_distance_error",
    "episode/success_rate",
    "episode/length",
    "episode/collisions_obstacle",
    "episode/collisions_agent",
    *(f"reward/{term}" for term in REWARD_TERMS),
]
