"""Per-episode uncertainty under lerobot-eval: the trace split into episodes, the eval-loop hooks, the file."""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pacdp.cli_errors import UserInputError
from lerobot_pacdp.eval_hooks import install, recording_episodes
from lerobot_pacdp.modeling_pacdp import PacdpPolicy
from lerobot_pacdp.uncertainty import ChunkUncertainty
from lerobot_pacdp.uncertainty_episodes import (
    UNCERTAINTY_FILE,
    EpisodeUncertainty,
    UncertaintyRecording,
    episodes_from_rollout,
    read_recording,
    write_recording,
)

from pacdp_testing import tiny_config


def _chunk(posterior: list[float], noise: list[float]) -> ChunkUncertainty:
    return ChunkUncertainty(torch.zeros(len(noise), 4, 2), torch.tensor(posterior), torch.tensor(noise))


def _done_and_success(ends: list[int], successes: list[bool], steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """LeRobot's cumulative `done` and per-step `success` for episodes ending at `ends`."""
    done = torch.zeros(len(ends), steps, dtype=torch.bool)
    success = torch.zeros(len(ends), steps, dtype=torch.bool)
    for env, (end, succeeded) in enumerate(zip(ends, successes, strict=True)):
        done[env, end:] = True
        success[env, end] = succeeded
    return done, success


def test_a_rollouts_trace_splits_into_episodes_that_end_at_their_first_done():
    trace = [_chunk([0.1, 0.2], [1.0, 2.0]), _chunk([0.3, 0.4], [3.0, 4.0]), _chunk([0.5, 0.6], [5.0, 6.0])]
    done, success = _done_and_success([5, 11], [True, False], steps=12)  # chunks of 4 actions at steps 0, 4, 8
    first, second = episodes_from_rollout(trace, done, success, [7, 8], 4, "robomimic", 0, first_episode_ix=10)
    assert first == EpisodeUncertainty("robomimic", 0, 10, 7, True, 6, (0, 4), pytest.approx((0.1, 0.3)), (1.0, 3.0))
    assert (second.episode_ix, second.seed, second.success, second.length) == (11, 8, False, 12)
    assert second.decision_steps == (0, 4, 8) and second.noise == (2.0, 4.0, 6.0)


class _FakePolicy:
    """What the hooks read of a pacdp policy: its config and the trace `reset()` empties."""

    def __init__(self, samples: int):
        self.config = tiny_config(uncertainty_samples=samples)
        self.uncertainty_trace: list[ChunkUncertainty] = []

    def reset(self):
        self.uncertainty_trace = []


def _fake_eval_module() -> SimpleNamespace:
    """LeRobot's evaluation functions reduced to their calls: batches of 2 envs, 8 steps, chunks every 4."""
    module = SimpleNamespace()

    def rollout(env, policy, seeds=None):
        policy.reset()
        if policy.config.uncertainty_samples:
            policy.uncertainty_trace += [_chunk([0.1, 0.2], [1.0, 1.0]), _chunk([0.3, 0.4], [1.0, 1.0])]
        return dict(zip(("done", "success"), _done_and_success([7, 3], [False, True], steps=8), strict=True))

    def run_one(task_group, task_id, env, *, policy, n_episodes, start_seed):
        for batch in range(-(-n_episodes // 2)):
            module.rollout(env=env, policy=policy, seeds=[start_seed + 2 * batch, start_seed + 2 * batch + 1])
        return task_group, task_id, {}

    module.rollout, module.run_one = rollout, run_one
    install(module)
    return module


def test_the_eval_loop_hooks_number_a_tasks_episodes_and_drop_the_last_batchs_surplus():
    module = _fake_eval_module()
    with recording_episodes() as recorder:
        module.run_one("robomimic", 0, None, policy=_FakePolicy(samples=2), n_episodes=3, start_seed=10)
    recording = recorder.recording()
    assert (recording.samples, recording.n_action_steps, recording.checkpoint) == (2, 4, None)
    assert recording.policy.startswith("pacdp PAC-DP")
    assert [(e.episode_ix, e.seed, e.success, e.length) for e in recording.episodes] == [
        (0, 10, False, 8), (1, 11, True, 4), (2, 12, False, 8),
    ]  # fmt: skip
    assert recording.episodes[1].decision_steps == (0,) and recording.episodes[2].posterior == pytest.approx((0.1, 0.3))


def test_nothing_is_recorded_without_the_option_or_outside_a_recording():
    module = _fake_eval_module()
    with recording_episodes() as recorder:
        module.run_one("robomimic", 0, None, policy=_FakePolicy(samples=0), n_episodes=2, start_seed=0)
    assert recorder.recording() is None
    assert module.run_one("robomimic", 0, None, policy=_FakePolicy(samples=2), n_episodes=2, start_seed=0)[0] == "robomimic"


def test_a_recording_round_trips_through_its_file_and_damaged_files_are_refused(tmp_path):
    episode = EpisodeUncertainty("robomimic", 0, 0, 3, True, 12, (0, 8), (0.1, 0.2), (0.3, 0.4))
    recording = UncertaintyRecording(8, 8, "pacdp PAC-DP", "ckpt", (episode, EpisodeUncertainty("", 0, 1, None, False, 9, (0,), None, (0.5,))))
    path = write_recording(tmp_path / UNCERTAINTY_FILE, recording)
    assert read_recording(path) == recording == read_recording(tmp_path)
    assert not recording.has_posterior

    payload = json.loads(path.read_text())
    payload["episodes"][0]["noise"] = [0.3, float("nan")]
    (tmp_path / "nan.json").write_text(json.dumps(payload))
    payload["episodes"][0]["noise"] = [0.3, 0.4]
    del payload["episodes"][0]["length"]
    (tmp_path / "missing.json").write_text(json.dumps(payload))
    (tmp_path / "other.json").write_text(json.dumps({"per_task": []}))
    (tmp_path / "truncated.json").write_text(path.read_text()[:100])
    for name, message in [
        ("nan.json", "noise is not a list of finite numbers"), ("missing.json", "is damaged (KeyError"),
        ("other.json", "is not an uncertainty recording"), ("truncated.json", "is not valid JSON"),
        ("absent.json", "does not exist; record episodes with `lerobot-eval"),
    ]:  # fmt: skip
        with pytest.raises(UserInputError, match=message.replace("(", r"\(")):
            read_recording(tmp_path / name)


def save_lift_checkpoint(path: Path) -> Path:
    """A tiny untrained PAC-DP checkpoint shaped for robomimic Lift (state 9, environment_state 10, action 7)."""
    config = tiny_config()
    sizes = {"observation.state": 9, "observation.environment_state": 10, "action": 7}
    config.input_features = {
        "observation.state": PolicyFeature(FeatureType.STATE, (9,)),
        "observation.environment_state": PolicyFeature(FeatureType.ENV, (10,)),
    }
    config.output_features = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
    torch.manual_seed(0)
    PacdpPolicy(config).save_pretrained(path)
    stats = {key: {"min": -torch.ones(n), "max": torch.ones(n)} for key, n in sizes.items()}
    for processor in make_pre_post_processors(config, dataset_stats=stats):
        processor.save_pretrained(path)
    return path


@pytest.mark.slow
def test_lerobot_eval_writes_each_episodes_uncertainty_beside_eval_info(tmp_path):
    """Through the installed `lerobot-eval`: LeRobot's plugin discovery is what installs the hook."""
    checkpoint = save_lift_checkpoint(tmp_path / "checkpoint")
    out = tmp_path / "eval"
    result = subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={checkpoint}", "--policy.device=cpu",
         "--policy.uncertainty_samples=3", "--env.type=robomimic", "--env.task=lift", "--env.episode_length=6",
         "--eval.n_episodes=3", "--eval.batch_size=2", "--eval.use_async_envs=false", "--seed=40", f"--output_dir={out}"],
        capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    info = json.loads((out / "eval_info.json").read_text())
    recording = read_recording(out / UNCERTAINTY_FILE)
    successes = info["per_task"][0]["metrics"]["successes"]
    assert [e.success for e in recording.episodes] == successes and len(successes) == 3
    assert [(e.episode_ix, e.seed, e.length) for e in recording.episodes] == [(0, 40, 6), (1, 41, 6), (2, 42, 6)]
    assert all(e.decision_steps == (0, 4) for e in recording.episodes)  # chunks of 4 actions
    assert all(min(e.posterior) > 0 and min(e.noise) > 0 for e in recording.episodes)
    assert (recording.samples, recording.checkpoint) == (3, str(checkpoint))
