"""PAC-DP (PAC-Bayesian Diffusion Policy) as a LeRobot policy plugin.

Importing this package registers the `pacdp` policy type with LeRobot and, inside a running
`lerobot-train`, installs the dataset hook of `train_hooks` (N of Eq. 9, state-only data from memory);
inside `lerobot-eval`, the hook of `eval_hooks` (per-episode uncertainty with `--policy.uncertainty_samples`).
It is kept light: heavy simulators (robosuite) are imported lazily by the modules that need them.
"""

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.eval_hooks import install_into_running_lerobot_eval
from lerobot_pacdp.robomimic import env_config as _robomimic_env_config  # noqa: F401  (registers --env.type=robomimic)
from lerobot_pacdp.train_hooks import install_into_running_lerobot_train

install_into_running_lerobot_train()
install_into_running_lerobot_eval()

__all__ = ["PacdpConfig"]
