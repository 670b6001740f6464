"""What this plugin adds to `lerobot-eval`: each episode's uncertainty, written beside eval_info.json.

With `--policy.uncertainty_samples=K` a pacdp policy keeps one `ChunkUncertainty` per generated chunk
(`policy.uncertainty_trace`, emptied by `policy.reset()` at every rollout). LeRobot passes no output
directory to the policy, so `install()` wraps three functions of its evaluation module:

- `rollout`: after each batched rollout, the trace is split into its episodes (`uncertainty_episodes`);
- `run_one` (one task of `eval_policy_all`): the task's episodes are numbered as in eval_info.json and the
  surplus of the last batch dropped, as LeRobot drops it;
- `eval_main`: the episodes are written to `<output_dir>/uncertainty.json` after eval_info.json.

Nothing is recorded or written for a policy without the option. `recording_episodes()` collects the same
episodes around any call of `eval_policy_all` (what `pacdp-uncertainty` does in-process).
"""

import contextlib
import functools
import inspect
import logging
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

from lerobot_pacdp.module_swaps import running_modules
from lerobot_pacdp.rollout_summary import describe_policy
from lerobot_pacdp.uncertainty_episodes import (
    UNCERTAINTY_FILE,
    EpisodeUncertainty,
    UncertaintyRecording,
    episodes_from_rollout,
    write_recording,
)

logger = logging.getLogger(__name__)

LEROBOT_EVAL_MODULE = "lerobot.scripts.lerobot_eval"
_HOOK_MARK = "_pacdp_eval_hook"


class EpisodeRecorder:
    """The episodes recorded while active, from every task, with the recording's header."""

    def __init__(self):
        self._lock = threading.Lock()
        self.episodes: list[EpisodeUncertainty] = []
        self._header: dict[str, Any] | None = None

    def add(self, episodes: list[EpisodeUncertainty], header: dict[str, Any] | None) -> None:
        with self._lock:
            self.episodes.extend(episodes)
            self._header = self._header or header

    def recording(self) -> UncertaintyRecording | None:
        if not self.episodes or self._header is None:
            return None
        return UncertaintyRecording(**self._header, episodes=tuple(self.episodes))


class _TaskEpisodes:
    """The episodes of one task of `eval_policy_all` (one thread each when tasks run in parallel)."""

    def __init__(self, task_group: str, task_id: int):
        self.task_group, self.task_id = task_group, task_id
        self.episodes: list[EpisodeUncertainty] = []
        self.header: dict[str, Any] | None = None

    def add_rollout(self, policy: Any, data: dict, seeds: list[int] | None) -> None:
        config = policy.config
        self.header = self.header or {
            "samples": config.uncertainty_samples,
            "n_action_steps": config.n_action_steps,
            "policy": describe_policy({"type": config.type, **vars(config)}),
            "checkpoint": None if config.pretrained_path is None else str(config.pretrained_path),
        }
        self.episodes += episodes_from_rollout(
            policy.uncertainty_trace, data["done"], data["success"], seeds, config.n_action_steps,
            self.task_group, self.task_id, first_episode_ix=len(self.episodes),
        )


_active: EpisodeRecorder | None = None
_current_task = threading.local()


@contextlib.contextmanager
def recording_episodes() -> Iterator[EpisodeRecorder]:
    """Collect the uncertainty of every episode LeRobot's `eval_policy_all` runs inside the block."""
    global _active
    previous, _active = _active, EpisodeRecorder()
    try:
        yield _active
    finally:
        _active = previous


def _recording_rollout(rollout: Callable) -> Callable:
    signature = inspect.signature(rollout)

    @functools.wraps(rollout)
    def rollout_recording_uncertainty(*args, **kwargs):
        data = rollout(*args, **kwargs)
        task: _TaskEpisodes | None = getattr(_current_task, "task", None)
        if task is not None:
            arguments = signature.bind(*args, **kwargs).arguments
            policy = arguments["policy"]
            if getattr(policy, "uncertainty_trace", None):
                task.add_rollout(policy, data, arguments.get("seeds"))
        return data

    setattr(rollout_recording_uncertainty, _HOOK_MARK, True)
    return rollout_recording_uncertainty


def _recording_run_one(run_one: Callable) -> Callable:
    signature = inspect.signature(run_one)

    @functools.wraps(run_one)
    def run_one_recording_uncertainty(*args, **kwargs):
        recorder = _active
        if recorder is None:
            return run_one(*args, **kwargs)
        arguments = signature.bind(*args, **kwargs).arguments
        task = _TaskEpisodes(arguments["task_group"], arguments["task_id"])
        _current_task.task = task
        try:
            result = run_one(*args, **kwargs)
        finally:
            _current_task.task = None
        recorder.add(task.episodes[: arguments["n_episodes"]], task.header)
        return result

    setattr(run_one_recording_uncertainty, _HOOK_MARK, True)
    return run_one_recording_uncertainty


def _writing_uncertainty(eval_main: Callable) -> Callable:
    """LeRobot's `eval_main` (parsed by LeRobot's own `parser.wrap`), then `uncertainty.json` beside eval_info.json."""
    from lerobot.configs import parser
    from lerobot.configs.eval import EvalPipelineConfig

    evaluate = eval_main.__wrapped__  # the function under LeRobot's parser.wrap

    def eval_main_writing_uncertainty(cfg: EvalPipelineConfig):
        with recording_episodes() as recorder:
            result = evaluate(cfg)
        recording = recorder.recording()
        if recording is not None:
            path = write_recording(Path(cfg.output_dir) / UNCERTAINTY_FILE, recording)
            logger.info("PAC-DP: per-episode uncertainty of %d episodes in %s", len(recording.episodes), path)
        return result

    wrapped = parser.wrap()(eval_main_writing_uncertainty)
    setattr(wrapped, _HOOK_MARK, True)
    return wrapped


def install(module: ModuleType) -> None:
    """Wrap LeRobot's evaluation module (`lerobot.scripts.lerobot_eval`); idempotent."""
    for name, wrap in (("rollout", _recording_rollout), ("run_one", _recording_run_one), ("eval_main", _writing_uncertainty)):
        current = getattr(module, name, None)
        if current is not None and not getattr(current, _HOOK_MARK, False):
            setattr(module, name, wrap(current))


def install_into_running_lerobot_eval() -> None:
    """Install into lerobot-eval when it is the running program, or wherever its module is loaded."""
    for module in running_modules(LEROBOT_EVAL_MODULE):
        install(module)
