"""Per-episode uncertainty of a rollout: what `lerobot-eval --policy.uncertainty_samples=K` writes beside
eval_info.json (`uncertainty.json`) and what `pacdp-uncertainty` reads.

A chunk is generated every `n_action_steps` environment steps (LeRobot's action queue), so an episode's
trace is one value per decision step: decision j is made at step j * n_action_steps and its value holds
for the chunk's actions.
"""

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from lerobot_pacdp.atomic_io import write_text_atomic
from lerobot_pacdp.cli_errors import UserInputError

if TYPE_CHECKING:  # the plugin's import stays light: lerobot-eval imports this module at start-up
    from lerobot_pacdp.uncertainty import ChunkUncertainty

UNCERTAINTY_FILE = "uncertainty.json"
FORMAT = "pacdp-uncertainty/1"
SIGNAL = (
    "sqrt(mean over the executed steps and action dims of the variance over K chunks), normalised action "
    "units; posterior: K weight samples from the acting chunk's initial noise; noise: K initial noises, "
    "posterior-mean weights"
)


@dataclass(frozen=True)
class EpisodeUncertainty:
    """One episode: its outcome and the signals at its decision steps (`posterior` None without a posterior)."""

    task_group: str
    task_id: int
    episode_ix: int
    seed: int | None
    success: bool
    length: int  # environment steps
    decision_steps: tuple[int, ...]
    posterior: tuple[float, ...] | None
    noise: tuple[float, ...]


@dataclass(frozen=True)
class UncertaintyRecording:
    """The contents of an `uncertainty.json`."""

    samples: int
    n_action_steps: int
    policy: str  # `rollout_summary.describe_policy`'s label
    checkpoint: str | None
    episodes: tuple[EpisodeUncertainty, ...]

    @property
    def has_posterior(self) -> bool:
        return all(e.posterior is not None for e in self.episodes)


def episodes_from_rollout(
    trace: Sequence["ChunkUncertainty"], done: torch.Tensor, success: torch.Tensor, seeds: Sequence[int] | None,
    n_action_steps: int, task_group: str = "", task_id: int = 0, first_episode_ix: int = 0,
) -> list[EpisodeUncertainty]:
    """Split a batched rollout's trace (one entry per chunk) into its episodes.

    `done` and `success` are (B, steps) as LeRobot's `rollout` returns them; an episode ends at its first
    `done` and succeeds as LeRobot counts it (any success up to the step after its end).
    """
    episodes = []
    for env in range(done.shape[0]):
        end = int(torch.argmax(done[env].to(int)))
        succeeded = bool(success[env, : end + 2].any())
        decisions = [j for j in range(len(trace)) if j * n_action_steps <= end]
        posterior = None if trace and trace[0].posterior is None else tuple(float(trace[j].posterior[env]) for j in decisions)
        episodes.append(
            EpisodeUncertainty(
                task_group=task_group,
                task_id=task_id,
                episode_ix=first_episode_ix + env,
                seed=None if seeds is None else int(seeds[env]),
                success=succeeded,
                length=end + 1,
                decision_steps=tuple(j * n_action_steps for j in decisions),
                posterior=posterior,
                noise=tuple(float(trace[j].noise[env]) for j in decisions),
            )
        )
    return episodes


def write_recording(path: Path, recording: UncertaintyRecording) -> Path:
    payload = {"format": FORMAT, "signal": SIGNAL, **asdict(recording)}
    return write_text_atomic(path, json.dumps(payload, indent=1) + "\n")


def _finite_values(values: object, where: str) -> tuple[float, ...]:
    if not isinstance(values, list) or not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
        raise UserInputError(f"{where} is not a list of finite numbers; record the episodes again.")
    return tuple(float(v) for v in values)


def read_recording(path: Path) -> UncertaintyRecording:
    """Read an `uncertainty.json` (or a directory holding one), refusing files of another kind."""
    path = Path(path)
    if path.is_dir():
        path = path / UNCERTAINTY_FILE
    try:
        payload = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserInputError(
            f"{path} does not exist; record episodes with `lerobot-eval ... --policy.uncertainty_samples=8` "
            "or `pacdp-uncertainty --checkpoint=...`."
        ) from None
    except json.JSONDecodeError as exc:
        raise UserInputError(f"{path} is not valid JSON ({exc.msg}); record the episodes again.") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise UserInputError(f"{path} is not an uncertainty recording ({FORMAT}); pass the {UNCERTAINTY_FILE} lerobot-eval wrote.")
    try:
        episodes = tuple(_episode(row, f"{path}: episode {i}") for i, row in enumerate(payload.get("episodes") or []))
        recording = UncertaintyRecording(
            samples=int(payload["samples"]), n_action_steps=int(payload["n_action_steps"]),
            policy=str(payload["policy"]), checkpoint=payload["checkpoint"], episodes=episodes,
        )
    except UserInputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UserInputError(f"{path} is damaged ({type(exc).__name__}: {exc}); record the episodes again.") from None
    if not episodes:
        raise UserInputError(f"{path} holds no episodes; record some with --policy.uncertainty_samples=8.")
    return recording


def _episode(row: dict, where: str) -> EpisodeUncertainty:
    noise = _finite_values(row.get("noise"), f"{where}'s noise")
    posterior = None if row.get("posterior") is None else _finite_values(row["posterior"], f"{where}'s posterior")
    steps = tuple(int(s) for s in row["decision_steps"])
    if len(steps) != len(noise) or (posterior is not None and len(posterior) != len(noise)):
        raise UserInputError(f"{where} has signals of different lengths; record the episodes again.")
    return EpisodeUncertainty(
        task_group=str(row["task_group"]),
        task_id=int(row["task_id"]),
        episode_ix=int(row["episode_ix"]),
        seed=None if row["seed"] is None else int(row["seed"]),
        success=bool(row["success"]),
        length=int(row["length"]),
        decision_steps=steps,
        posterior=posterior,
        noise=noise,
    )
