"""Discovery shim: LeRobot imports the module named like the distribution (`lerobot_policy_pacdp`).

Importing it registers the `pacdp` policy (and this package's env types) with LeRobot, and makes
LeRobot's CLIs print this package's config errors as written (`cli_errors.name_plugin_config_errors`).
"""

import lerobot_pacdp  # noqa: F401
from lerobot_pacdp.cli_errors import name_plugin_config_errors

name_plugin_config_errors()
