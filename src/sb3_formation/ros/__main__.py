"""``python -m sb3_formation.ros``: the simulator node or a team's agent nodes (:mod:`sb3_formation.ros.launch`)."""

import sys

from sb3_formation.ros.launch import main

sys.exit(main())
