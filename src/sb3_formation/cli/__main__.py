"""``python -m sb3_formation.cli``."""

import sys

from sb3_formation.cli import main

sys.exit(main())
