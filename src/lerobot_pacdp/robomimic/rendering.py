"""Choose MuJoCo's offscreen OpenGL backend before robosuite is imported, so rollout videos work headless.

robosuite sets `MUJOCO_GL=egl` at import unless it is already `osmesa` or `glx`; on a machine without a
GPU that EGL context fails and every frame would be blank. Unless the user set `MUJOCO_GL`, pick EGL where
a GPU device node and libEGL exist, else OSMesa (CPU; Debian's `libosmesa6`) where it is installed, else
nothing (the env then records blank frames and says why once).
"""

import ctypes.util
import glob
import os
import sys


def choose_mujoco_gl() -> str | None:
    """Set `MUJOCO_GL` (and `PYOPENGL_PLATFORM`) if unset and MuJoCo is not loaded yet; returns the backend."""
    chosen = os.environ.get("MUJOCO_GL")
    if chosen or "mujoco" in sys.modules:
        return chosen or None
    gpu = glob.glob("/dev/nvidia[0-9]*") or glob.glob("/dev/dri/renderD*")
    if gpu and ctypes.util.find_library("EGL"):
        chosen = "egl"
    elif ctypes.util.find_library("OSMesa"):
        chosen = "osmesa"
    else:
        return None
    os.environ["MUJOCO_GL"] = chosen
    os.environ.setdefault("PYOPENGL_PLATFORM", chosen)
    return chosen
