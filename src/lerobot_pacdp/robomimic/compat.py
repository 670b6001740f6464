"""Compatibility between robomimic files recorded with robosuite <= 1.4 and robosuite 1.5.

The released robomimic datasets were recorded with robosuite 1.2 (v0.1 files) or 1.4 (the `_v141`
files); this package simulates with robosuite 1.5. Five things differ, and a policy trained on an old
file sees the world through the old conventions, so rollouts in 1.5 must be translated back:

1. Lift: `gripper_to_cube_pos` changed sign (eef - cube in <= 1.4, cube - eef in 1.5).
2. Can, Square, ToolHang: the per-object block of `object` changed order from
   [pos, quat, to_eef_pos, to_eef_quat] (<= 1.4) to [to_eef_pos, to_eef_quat, pos, quat] (1.5).
3. Transport: the two boolean flags moved from the end of `object` to just after `trash_bin_pos`; and the
   robot bases are rotated +-90 deg in 1.5, whose OSC controller reads deltas in the base frame by
   default, while old files hold world-frame deltas -> `input_ref_frame="world"` for every arm.
4. robosuite 1.5 returns zeros for the `*_to_robot0_eef_*` fields in the observation `reset()` returns,
   and after a state restore one forced update pairs them with the previous state's object poses; two
   forced updates (`env.current_observations`) give the right values. (The gym environment always does
   this, in both modes, after resets and `set_state`.)
5. Seeding: robosuite 1.5.2 draws object placements from `env.rng` / the samplers' `rng`, older ones
   (and 1.5.1, which this project pins) from numpy's global generator. The gym environment seeds both.

Generation labels: `"1.5"` (robosuite >= 1.5, the environment's native layout) and `"1.4"` (any
robosuite <= 1.4, including the 1.2 files). Importing this module is cheap (no robosuite).
"""

import functools
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from lerobot_pacdp.robomimic.tasks import RobomimicTask, get_task

NATIVE = "1.5"
LEGACY = "1.4"
GENERATIONS = (NATIVE, LEGACY)

# Observables whose sign differs between generations (difference 1).
_NEGATED_IN_LEGACY: dict[str, tuple[str, ...]] = {"lift": ("gripper_to_cube_pos",)}


def normalize_generation(value: Any) -> str:
    """Map user input (`1.4`, `"1.4.1"`, `"<=1.4"`, `1.5`, `"native"`, `"legacy"`) to "1.5" or "1.4"."""
    text = str(value).strip().lower().lstrip("<=v ")
    if text in ("native", "new", "none", ""):
        return NATIVE
    if text in ("legacy", "old"):
        return LEGACY
    version = _parse_version(text)
    if version is None or version[0] != 1:
        raise ValueError(
            f"robosuite_compat must be '1.5' (native robosuite 1.5 layout) or '1.4' (datasets recorded with "
            f"robosuite <= 1.4, e.g. the released robomimic files), got {value!r}."
        )
    return NATIVE if version >= (1, 5) else LEGACY


def _parse_version(text: str | None) -> tuple[int, int] | None:
    match = re.match(r"^\s*v?(\d+)\.(\d+)", str(text)) if text is not None else None
    return (int(match.group(1)), int(match.group(2))) if match else None


def legacy_object_layout(task: RobomimicTask | str) -> tuple[tuple[str, int], ...]:
    """The `object` layout of files recorded with robosuite <= 1.4 (differences 2 and 3)."""
    task = get_task(task) if isinstance(task, str) else task
    layout = list(task.object_layout)
    if task.name in ("can", "square", "tool_hang"):
        flags = [item for item in layout if item[1] == 1]
        blocks = [layout[i : i + 4] for i in range(0, len(layout) - len(flags), 4)]
        reordered = []
        for to_eef_pos, to_eef_quat, pos, quat in blocks:
            reordered += [pos, quat, to_eef_pos, to_eef_quat]
        return tuple(reordered + flags)
    if task.name == "transport":
        flags = [item for item in layout if item[1] == 1]
        return tuple([item for item in layout if item[1] != 1] + flags)
    return tuple(layout)


def object_layout(task: RobomimicTask | str, generation: str = NATIVE) -> tuple[tuple[str, int], ...]:
    task = get_task(task) if isinstance(task, str) else task
    return task.object_layout if normalize_generation(generation) == NATIVE else legacy_object_layout(task)


@functools.cache
def _permutation(task: RobomimicTask) -> np.ndarray:
    """Indices `p` such that `legacy = native[..., p]` (before sign changes)."""
    starts, start = {}, 0
    for key, size in task.object_layout:
        starts[key] = (start, size)
        start += size
    return np.concatenate([np.arange(starts[k][0], starts[k][0] + starts[k][1]) for k, _ in legacy_object_layout(task)])


@functools.cache
def _legacy_signs(task: RobomimicTask) -> np.ndarray:
    """+-1 per dimension of the legacy layout (difference 1)."""
    negated = _NEGATED_IN_LEGACY.get(task.name, ())
    return np.concatenate([np.full(size, -1.0 if key in negated else 1.0) for key, size in legacy_object_layout(task)])


def object_to_legacy(task: RobomimicTask | str, native: np.ndarray) -> np.ndarray:
    """Translate robosuite 1.5 `object` vector(s) (..., D) into the robosuite <= 1.4 layout."""
    task = get_task(task) if isinstance(task, str) else task
    native = np.asarray(native)
    _check_width(task, native)
    return native[..., _permutation(task)] * _legacy_signs(task).astype(native.dtype, copy=False)


def object_from_legacy(task: RobomimicTask | str, legacy: np.ndarray) -> np.ndarray:
    """Inverse of `object_to_legacy`: robosuite <= 1.4 `object` vector(s) -> robosuite 1.5 layout."""
    task = get_task(task) if isinstance(task, str) else task
    legacy = np.asarray(legacy)
    _check_width(task, legacy)
    out = np.empty_like(legacy)
    out[..., _permutation(task)] = legacy * _legacy_signs(task).astype(legacy.dtype, copy=False)
    return out


def _check_width(task: RobomimicTask, vector: np.ndarray) -> None:
    if vector.shape[-1] != task.object_dim:
        raise ValueError(
            f"{task.name}: an object vector has {task.object_dim} entries, got shape {vector.shape}."
        )


def controller_input_ref_frame(generation: str) -> str:
    """OSC delta frame: old files hold world-frame deltas (difference 3), 1.5's default is the base frame."""
    return "world" if normalize_generation(generation) == LEGACY else "base"


def file_generation(
    env_args: Mapping[str, Any] | None, repository_version: str | None = None
) -> tuple[str, str | None]:
    """Which robosuite generation recorded a robomimic file: ("1.5" | "1.4", exact version or None).

    Uses, in order: `env_args["env_version"]` (written by robomimic >= 0.3), the `data` group's
    `repository_version` attribute (written by robosuite's own collection scripts), then the controller
    config's shape (robosuite 1.5 composite configs have `body_parts`; older ones are a flat
    `{"type": "OSC_POSE", ...}`). A file without any of these is from the robosuite 1.2 era.
    """
    env_args = env_args or {}
    for version in (env_args.get("env_version"), repository_version):
        if version and _parse_version(str(version)) is not None:
            return (NATIVE if _parse_version(str(version)) >= (1, 5) else LEGACY), str(version)
    controller = (env_args.get("env_kwargs") or {}).get("controller_configs")
    composite_keys = ("body_parts", "body_parts_controller_configs")
    if isinstance(controller, Mapping) and any(key in controller for key in composite_keys):
        return NATIVE, None
    return LEGACY, None
