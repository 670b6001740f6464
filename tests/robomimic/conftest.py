"""Shared robomimic fixtures. robosuite environments are expensive to create (the first one in a process
also JIT-compiles robosuite's numba helpers), so they are shared at session scope."""

import pytest

from lerobot_pacdp.robomimic.hdf5_format import write_robomimic_hdf5


def _session_env(task: str, **kwargs):
    from lerobot_pacdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv(task, **kwargs)
    yield env
    env.close()


@pytest.fixture(scope="session")
def lift_env():
    yield from _session_env("lift")


@pytest.fixture(scope="session")
def lift_env_legacy():
    yield from _session_env("lift", robosuite_compat="1.4", render_mode=None)


@pytest.fixture(scope="session")
def square_env():
    yield from _session_env("square", render_mode=None)


@pytest.fixture(scope="session")
def square_env_legacy():
    yield from _session_env("square", robosuite_compat="1.4", render_mode=None)


@pytest.fixture(scope="session")
def scripted_lift(tmp_path_factory):
    """(hdf5 path, demos, stats): 4 scripted Lift demos with action noise, in robomimic format."""
    from lerobot_pacdp.robomimic.hdf5_format import split_masks
    from lerobot_pacdp.robomimic.scripted_experts import collect_demos

    demos, stats, env_args = collect_demos("lift", 4, seed=7, action_noise=0.05)
    path = tmp_path_factory.mktemp("scripted") / "lift.hdf5"
    write_robomimic_hdf5(path, demos, env_args, split_masks(len(demos), 0.25, seed=7))
    return path, demos, stats


@pytest.fixture(scope="session")
def scripted_lift_dataset(scripted_lift, tmp_path_factory):
    from lerobot_pacdp.robomimic.hdf5_adapter import convert_robomimic_hdf5

    root = tmp_path_factory.mktemp("datasets") / "lift"
    return convert_robomimic_hdf5(scripted_lift[0], root)
