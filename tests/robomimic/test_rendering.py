"""The offscreen renderer is chosen before robosuite would force EGL."""

import ctypes.util
import glob
import sys

import pytest

from lerobot_pacdp.robomimic import rendering


@pytest.fixture
def fresh_process(monkeypatch):
    """As if MuJoCo were not imported yet and the user had set no backend."""
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.delitem(sys.modules, "mujoco", raising=False)
    return monkeypatch


def _machine(monkeypatch, libraries: set[str], devices: list[str]) -> None:
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: f"lib{name}.so" if name in libraries else None)
    monkeypatch.setattr(glob, "glob", lambda pattern: [d for d in devices if d.startswith(pattern.split("[")[0].rstrip("*"))])


def test_a_cpu_machine_with_libosmesa_renders_with_osmesa(fresh_process):
    _machine(fresh_process, {"OSMesa", "EGL"}, devices=[])
    assert rendering.choose_mujoco_gl() == "osmesa"
    import os

    assert os.environ["MUJOCO_GL"] == "osmesa" and os.environ["PYOPENGL_PLATFORM"] == "osmesa"


def test_a_gpu_machine_renders_with_egl(fresh_process):
    _machine(fresh_process, {"OSMesa", "EGL"}, devices=["/dev/nvidia0"])
    assert rendering.choose_mujoco_gl() == "egl"


def test_without_any_offscreen_library_nothing_is_set(fresh_process):
    _machine(fresh_process, set(), devices=[])
    assert rendering.choose_mujoco_gl() is None
    import os

    assert "MUJOCO_GL" not in os.environ


def test_the_users_choice_is_kept(fresh_process):
    fresh_process.setenv("MUJOCO_GL", "glx")
    _machine(fresh_process, {"OSMesa"}, devices=[])
    assert rendering.choose_mujoco_gl() == "glx"
