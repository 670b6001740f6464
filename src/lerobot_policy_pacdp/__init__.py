"""Discovery shim: LeRobot imports the module named like the distribution (`lerobot_policy_pacdp`).

Importing it registers the `pacdp` policy (and this package's env types) with LeRobot.
"""

import lerobot_pacdp  # noqa: F401
