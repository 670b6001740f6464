"""PushT block geometry, taken from gym_pusht itself so converted demos match what the simulator observes.

The T's shapes, keypoint order and coverage measure all come from `gym_pusht.envs.pusht`; only the goal
pose and the success threshold are restated here, because gym_pusht keeps them as instance attributes
of a live env rather than as importable constants (the tests check they agree).
"""

import warnings
from functools import cache

import numpy as np
import pymunk
from shapely.geometry import MultiPolygon

with warnings.catch_warnings():
    # pygame (imported by gym_pusht) warns about pkg_resources on import; not actionable for our users.
    warnings.filterwarnings("ignore", message="pkg_resources is deprecated", category=UserWarning)
    from gym_pusht.envs.pusht import PushTEnv, pymunk_to_shapely

GOAL_POSE = np.array([256.0, 256.0, np.pi / 4])  # x, y, angle of the target T (PushTEnv._setup)
SUCCESS_THRESHOLD = 0.95  # goal coverage above which PushTEnv counts an episode as solved
NUM_KEYPOINTS = 8  # corners of the T's two rectangles, in PushTEnv.get_keypoints order


@cache
def _tee() -> tuple[pymunk.Body, list[pymunk.Poly], MultiPolygon]:
    """One reusable T body (its shapes) and the goal T's shapely geometry, built by gym_pusht."""
    body, shapes = PushTEnv.add_tee(pymunk.Space(), (0.0, 0.0), 0.0)
    goal = pymunk_to_shapely(PushTEnv.get_goal_pose_body(GOAL_POSE), shapes)
    return body, shapes, goal


def keypoints_and_coverage(block_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T keypoints (N, 16) and goal coverage (N,) for block poses (N, 3) = x, y, angle of the body origin.

    The pose is what PushTEnv reports as `block.position`/`block.angle` (the body origin, not its centre of
    gravity), which is also what Diffusion Policy's replay buffer recorded. Setting the angle before the
    position places the origin exactly at (x, y), as `PushTEnv.add_tee` does.
    """
    poses = np.asarray(block_poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"block poses must have shape (N, 3) = x, y, angle; got {poses.shape}")
    body, shapes, goal = _tee()
    keypoints = np.empty((len(poses), 2 * NUM_KEYPOINTS))
    coverage = np.empty(len(poses))
    for i, (x, y, angle) in enumerate(poses):
        body.angle = angle
        body.position = (x, y)
        keypoints[i] = PushTEnv.get_keypoints(shapes).reshape(-1)
        coverage[i] = goal.intersection(pymunk_to_shapely(body, shapes)).area / goal.area
    return keypoints, coverage


def reward_and_success(coverage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PushTEnv.step's reward (coverage scaled so the success threshold maps to 1) and success flag."""
    coverage = np.asarray(coverage, dtype=np.float64)
    return np.clip(coverage / SUCCESS_THRESHOLD, 0.0, 1.0), coverage > SUCCESS_THRESHOLD
