"""Out-of-distribution check of the uncertainty on robomimic: the signal at the first decision of episodes
whose object starts beyond the demonstrations' initial-state range, against unshifted starts.

robosuite samples the task's first object uniformly in a small box (Lift: +-0.03 m in x and y); the
scripted and released demonstrations start from that box. A shifted start moves the object by `shift`
metres in a random horizontal direction after the seeded reset, so every shift shares the robot's state
and the object's orientation with its unshifted start.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation

from lerobot_pacdp.failure_prediction import auroc
from lerobot_pacdp.robomimic.env import RobomimicEnv, observation_vectors


@dataclass(frozen=True)
class ShiftedStarts:
    shift: float  # metres
    n_states: int
    posterior: tuple[float, ...] | None
    noise: tuple[float, ...]


@dataclass(frozen=True)
class OodComparison:
    shift: float
    n_states: int
    posterior_mean: float | None
    noise_mean: float
    posterior_auroc: float | None  # shifted (positive) vs unshifted starts
    noise_auroc: float


def initial_observations(env: RobomimicEnv, seeds: Sequence[int], shift: float) -> dict[str, np.ndarray]:
    """The raw observations (`agent_pos`, `environment_state`) of the seeded starts, the first object moved."""
    robosuite_env = env.robosuite_env
    states, objects = [], []
    for seed in seeds:
        observation, _ = env.reset(seed=int(seed))
        if shift > 0:
            joint = robosuite_env.model.mujoco_objects[0].joints[0]
            start, _ = robosuite_env.sim.model.get_joint_qpos_addr(joint)
            angle = np.random.default_rng(int(seed)).uniform(0.0, 2.0 * math.pi)
            flat = env.get_state()  # [time, qpos, qvel]
            flat[1 + start : 3 + start] += shift * np.array([math.cos(angle), math.sin(angle)])
            raw = env.set_state(flat)
            agent_pos, environment_state = observation_vectors(env.robomimic_task, raw, env.generation)
            observation = {"agent_pos": agent_pos, "environment_state": environment_state}
        states.append(observation["agent_pos"])
        objects.append(observation["environment_state"])
    return {"agent_pos": np.stack(states), "environment_state": np.stack(objects)}


@torch.no_grad()
def first_decision_uncertainty(
    policy, preprocessor, observations: dict[str, np.ndarray], num_samples: int, batch_size: int
) -> tuple[list[float] | None, list[float]]:
    """The posterior and noise spreads of the first chunk a freshly reset policy generates for each start."""
    posterior, noise = [], []
    total = len(observations["agent_pos"])
    for first in range(0, total, batch_size):
        rows = {key: value[first : first + batch_size] for key, value in observations.items()}
        batch = preprocessor(preprocess_observation(rows))
        policy.reset()
        chunk = policy.predict_with_uncertainty(
            {k: v.unsqueeze(1).expand(-1, policy.config.n_obs_steps, *v.shape[1:]) for k, v in batch.items()
             if k in policy.config.input_features},
            num_samples=num_samples,
        )
        if chunk.posterior is not None:
            posterior += chunk.posterior.tolist()
        noise += chunk.noise.tolist()
    return (posterior or None), noise


def shifted_starts(
    policy, preprocessor, task: str, robosuite_compat: str, seeds: Sequence[int], shifts: Sequence[float],
    num_samples: int, batch_size: int,
) -> list[ShiftedStarts]:
    """The first-decision signals of `seeds` at shift 0 and at each of `shifts`."""
    env = RobomimicEnv(task, robosuite_compat=robosuite_compat, render_mode=None)
    try:
        results = []
        for shift in [0.0, *shifts]:
            observations = initial_observations(env, seeds, shift)
            posterior, noise = first_decision_uncertainty(policy, preprocessor, observations, num_samples, batch_size)
            results.append(ShiftedStarts(shift, len(seeds), None if posterior is None else tuple(posterior), tuple(noise)))
        return results
    finally:
        env.close()


def compare_to_unshifted(results: Sequence[ShiftedStarts]) -> list[OodComparison]:
    """Mean signal per shift and the AUROC separating each shifted set from the unshifted one."""
    base = results[0]
    comparisons = []
    for result in results:
        has_posterior = result.posterior is not None and base.posterior is not None
        comparisons.append(
            OodComparison(
                shift=result.shift,
                n_states=result.n_states,
                posterior_mean=float(np.mean(result.posterior)) if has_posterior else None,
                noise_mean=float(np.mean(result.noise)),
                posterior_auroc=auroc(result.posterior, base.posterior) if has_posterior else None,
                noise_auroc=auroc(result.noise, base.noise),
            )
        )
    return comparisons
