"""PAC-DP (PAC-Bayesian Diffusion Policy) as a LeRobot policy plugin.

Importing this package registers the `pacdp` policy type with LeRobot. It is kept light: heavy
simulators (robosuite) are imported lazily by the modules that need them.
"""

from lerobot_pacdp.configuration_pacdp import PacdpConfig

__all__ = ["PacdpConfig"]
