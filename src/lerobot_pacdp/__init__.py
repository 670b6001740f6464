"""PAC-DP (PAC-Bayesian Diffusion Policy) as a LeRobot policy plugin.

Importing this package registers the `pacdp` policy type with LeRobot. It is kept light: heavy
simulators (robosuite) are imported lazily by the modules that need them.
"""

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.robomimic import env_config as _robomimic_env_config  # noqa: F401  (registers --env.type=robomimic)

__all__ = ["PacdpConfig"]
