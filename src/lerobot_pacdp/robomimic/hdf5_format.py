"""Writing robomimic-format hdf5 files (the schema of the released `low_dim.hdf5` files).

    data            attrs: total (frames), env_args (JSON: env_name, env_version, type, env_kwargs)
    data/demo_i     attrs: num_samples, model_file; datasets: states (T, S), actions (T, A),
                    rewards (T,), dones (T,); groups obs/<key>, next_obs/<key> with (T, ...) arrays
    mask/<filter>   demo names (bytes), e.g. mask/train, mask/valid
"""

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_pacdp.atomic_io import staged_file

ENV_TYPE_ROBOSUITE = 1  # robomimic's EnvType.ROBOSUITE_TYPE


@dataclass
class Demo:
    """One demonstration: `obs[key][t]` is observed before `actions[t]`, `next_obs[key][t]` after it."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    model_file: str = ""
    extra_attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.actions)


def split_masks(num_demos: int, valid_fraction: float = 0.1, seed: int = 0) -> dict[str, list[str]]:
    """robomimic's `split_train_val_from_hdf5`: a seeded random `valid_fraction` of demos in mask/valid."""
    names = [f"demo_{i}" for i in range(num_demos)]
    num_valid = int(round(num_demos * valid_fraction)) if num_demos > 1 else 0
    order = np.random.default_rng(seed).permutation(num_demos)
    valid = set(order[:num_valid].tolist())
    return {
        "train": [names[i] for i in range(num_demos) if i not in valid],
        "valid": [names[i] for i in range(num_demos) if i in valid],
    }


def write_robomimic_hdf5(
    path: str | Path,
    demos: Sequence[Demo],
    env_args: Mapping,
    masks: Mapping[str, Sequence[str]] | None = None,
    data_attrs: Mapping | None = None,
) -> Path:
    """Write `demos` as `data/demo_0..N-1` with the given `env_args` and masks (default: a 90/10 split)."""
    import h5py

    path = Path(path)
    masks = split_masks(len(demos)) if masks is None else masks
    with staged_file(path) as tmp, h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        total = 0
        for i, demo in enumerate(demos):
            group = data.create_group(f"demo_{i}")
            group.attrs["num_samples"] = len(demo)
            if demo.model_file:
                group.attrs["model_file"] = demo.model_file
            for key, value in demo.extra_attrs.items():
                group.attrs[key] = value
            group.create_dataset("states", data=np.asarray(demo.states, dtype=np.float64))
            group.create_dataset("actions", data=np.asarray(demo.actions, dtype=np.float64))
            group.create_dataset("rewards", data=np.asarray(demo.rewards, dtype=np.float64))
            group.create_dataset("dones", data=np.asarray(demo.dones, dtype=np.int64))
            for name, obs in (("obs", demo.obs), ("next_obs", demo.next_obs)):
                obs_group = group.create_group(name)
                for key, value in obs.items():
                    obs_group.create_dataset(key, data=np.asarray(value))
            total += len(demo)
        data.attrs["total"] = total
        data.attrs["env_args"] = json.dumps(dict(env_args))
        for key, value in (data_attrs or {}).items():
            data.attrs[key] = value
        mask = f.create_group("mask")
        for name, demo_names in masks.items():
            mask.create_dataset(name, data=np.array([n.encode() for n in demo_names], dtype="S"))
    return path
