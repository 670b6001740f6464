"""What this plugin changes inside `lerobot-train`: how the training datasets are made, and nothing else.

LeRobot imports plugins at the start of `lerobot-train`'s `main()`, after its training module is loaded.
`install()` then wraps that module's `make_train_eval_datasets` (LeRobot's own function still builds the
datasets) so that, before the policy is made:

1. a pacdp policy with no `num_train_samples` gets N of Eq. 9 from the training dataset it will train on
   (`training_set.training_windows`), and the log says how it was counted;
2. a state-only dataset is served from memory (`in_memory_data.InMemoryStateDataset`, the same items as
   LeRobotDataset) when the policy is pacdp, or for any policy type when `PACDP_IN_MEMORY_DATA=1` (what
   the study sets for LeRobot's `diffusion`, so baselines read data the same way); `PACDP_IN_MEMORY_DATA=0`
   turns it off. Image, video and language datasets keep LeRobot's path. Other policy types are untouched
   unless asked.
"""

import functools
import logging
import os
import sys
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any

import torch
from lerobot.datasets import EpisodeAwareSampler

from lerobot_pacdp.configuration_pacdp import PacdpConfig
from lerobot_pacdp.module_swaps import running_modules

logger = logging.getLogger(__name__)

IN_MEMORY_DATA_ENV = "PACDP_IN_MEMORY_DATA"
LEROBOT_TRAIN_MODULE = "lerobot.scripts.lerobot_train"
_HOOK_MARK = "_pacdp_train_hook"


def in_memory_data_wanted(policy_type: str | None) -> bool:
    """pacdp by default; any policy type with PACDP_IN_MEMORY_DATA=1; none with PACDP_IN_MEMORY_DATA=0."""
    flag = os.environ.get(IN_MEMORY_DATA_ENV)
    if flag is not None and flag.strip():
        return flag.strip().lower() not in ("0", "false", "no", "off")
    return policy_type == "pacdp"


def check_observations(features: dict) -> None:
    """What LeRobot's diffusion policy needs of a dataset, said before it fails deep inside `make_policy`."""
    from lerobot_pacdp.cli_errors import UserInputError

    if "observation.state" not in features:
        raise UserInputError(
            f"the dataset has no `observation.state` (it has {sorted(features)}); pacdp, like LeRobot's "
            "diffusion policy, conditions on the robot state: convert the data with pacdp-convert-pusht or "
            "pacdp-convert-robomimic, or rename the state feature with --rename_map."
        )
    if "observation.environment_state" not in features and not any(
        f.get("dtype") in ("image", "video") for f in features.values()
    ):
        raise UserInputError(
            "the dataset has `observation.state` but neither `observation.environment_state` nor a camera; "
            "pacdp needs one of them (state-based: the object/keypoint vector as observation.environment_state)."
        )


def prepare_training_datasets(cfg: Any, train: Any, eval_: Any) -> tuple[Any, Any]:
    """Set N for a pacdp policy and serve state-only datasets from memory (see the module docstring)."""
    from lerobot_pacdp.training_set import training_windows

    policy_cfg = getattr(cfg, "policy", None)
    if isinstance(policy_cfg, PacdpConfig):
        check_observations(train.meta.features)
    if isinstance(policy_cfg, PacdpConfig) and policy_cfg.num_train_samples is None:
        size = training_windows(train, policy_cfg.drop_n_last_frames)
        policy_cfg.num_train_samples = size.num_windows
        logger.info("PAC-DP: N = %d (%d episodes; %s).", size.num_windows, size.num_episodes, size.source)

    if not in_memory_data_wanted(getattr(policy_cfg, "type", None)):
        return train, eval_
    from lerobot_pacdp.in_memory_data import InMemoryStateDataset, unsupported_reason

    reason = unsupported_reason(train)
    if reason is not None:
        logger.info("PAC-DP: LeRobot's data path is kept: %s.", reason)
        return train, eval_
    train = InMemoryStateDataset(train)
    if eval_ is not None and unsupported_reason(eval_) is None:
        eval_ = InMemoryStateDataset(eval_)
    logger.info("PAC-DP: serving the state-only dataset from memory (%d frames).", len(train))
    return train, eval_


def _episode_sampler(loader: Any) -> EpisodeAwareSampler | None:
    """The EpisodeAwareSampler under a (possibly accelerate-prepared) DataLoader, if there is one."""
    candidates = [getattr(loader, "sampler", None)]
    batch_sampler = getattr(loader, "batch_sampler", None)
    while batch_sampler is not None:
        candidates.append(getattr(batch_sampler, "sampler", None))
        batch_sampler = getattr(batch_sampler, "batch_sampler", None)
    return next((c for c in candidates if isinstance(c, EpisodeAwareSampler)), None)


def resumable_cycle(loader: Any) -> Iterator[Any]:
    """LeRobot's `cycle` over the training DataLoader, made exact on `--resume=true`. Two LeRobot 0.6.1 bugs:

    - resume loads the sampler's epoch, but accelerate's DataLoaderShard sets the sampler's epoch to its
      own pass counter (0) when the first pass starts, so the resumed run replays epoch 0's order from the
      saved offset: the counter is set to the loaded epoch first;
    - LeRobot restores the global torch RNG, but the resumed run starts a DataLoader pass (which draws a
      base seed from the global RNG) where the uninterrupted run did not, shifting every later noise and
      weight draw: each pass starts under a forked RNG, so passes do not consume the global stream.
    """
    sampler = _episode_sampler(loader)
    if sampler is not None and hasattr(loader, "iteration"):
        loader.iteration = sampler.state_dict()["epoch"]
    while True:
        iterator = iter(loader)
        with torch.random.fork_rng(devices=[]):
            first = next(iterator)  # the pass starts here: sampler epoch, base seed, first batch
        yield first
        yield from iterator


def _wrap(make_train_eval_datasets: Callable) -> Callable:
    def make_train_eval_datasets_for_pacdp(cfg):
        train, eval_ = make_train_eval_datasets(cfg)
        return prepare_training_datasets(cfg, train, eval_)

    setattr(make_train_eval_datasets_for_pacdp, _HOOK_MARK, True)
    make_train_eval_datasets_for_pacdp.__wrapped__ = make_train_eval_datasets
    return make_train_eval_datasets_for_pacdp


def _one_line_errors(train: Callable) -> Callable:
    """`train` with this plugin's own stops (bad input, a non-finite step, a config value it refuses after
    parsing, e.g. `--policy.path=X --policy.kl_weight=-1`) printed as one `lerobot-train: error:` line and
    exit status 2, instead of a traceback through LeRobot."""
    from lerobot_pacdp.cli_errors import (
        EXIT_USER_ERROR,
        UserInputError,
        plugin_config_error,
        raised_in_this_package,
    )
    from lerobot_pacdp.modeling_pacdp import NonFiniteTrainingError

    @functools.wraps(train)
    def train_naming_plugin_errors(*args, **kwargs):
        try:
            return train(*args, **kwargs)
        except Exception as exc:
            ours = isinstance(exc, UserInputError | NonFiniteTrainingError)
            ours = ours or (isinstance(exc, ValueError) and raised_in_this_package(exc))
            message = exc if ours else plugin_config_error(exc)  # a config value refused while LeRobot parses
            if message is None:
                raise
        print(f"lerobot-train: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USER_ERROR)

    setattr(train_naming_plugin_errors, _HOOK_MARK, True)
    return train_naming_plugin_errors


def install(module: ModuleType) -> None:
    """Wrap LeRobot's training script module (`lerobot.scripts.lerobot_train`); idempotent."""
    current = getattr(module, "make_train_eval_datasets", None)
    if current is not None and not getattr(current, _HOOK_MARK, False):
        module.make_train_eval_datasets = _wrap(current)
    if hasattr(module, "cycle"):
        module.cycle = resumable_cycle
    train = getattr(module, "train", None)
    if train is not None and not getattr(train, _HOOK_MARK, False):
        module.train = _one_line_errors(train)


def install_into_running_lerobot_train() -> None:
    """Install into lerobot-train when it is the running program (`lerobot-train`, `python -m`, torchrun)."""
    for module in running_modules(LEROBOT_TRAIN_MODULE):
        install(module)
