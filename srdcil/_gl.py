"""Headless OpenGL choice for MuJoCo rendering (imported first by ``srdcil``)."""
import os
import sys


def _pick_headless_gl() -> None:
    """Without a display, MuJoCo defaults to glfw, which cannot render. Before mujoco is imported,
    choose EGL when a GPU device is visible, else OSMesa when its library is installed. An explicit
    ``MUJOCO_GL`` is always kept; if nothing fits, rendering is reported unavailable (never a crash)."""
    if "MUJOCO_GL" in os.environ or os.environ.get("DISPLAY") or "mujoco" in sys.modules:
        return
    import ctypes.util

    gpu = os.path.exists("/dev/dri") or os.path.exists("/dev/nvidia0")
    if gpu and ctypes.util.find_library("EGL"):
        backend = "egl"
    elif ctypes.util.find_library("OSMesa"):
        backend = "osmesa"
    else:
        return
    had_platform = "PYOPENGL_PLATFORM" in os.environ
    os.environ["MUJOCO_GL"] = backend
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    try:  # mujoco picks its GL context at import and raises there if the backend cannot load
        import mujoco  # noqa: F401
    except Exception:  # noqa: BLE001 - fall back to mujoco's own default
        for name in [m for m in sys.modules if m == "mujoco" or m.startswith(("mujoco.", "OpenGL"))]:
            del sys.modules[name]
        del os.environ["MUJOCO_GL"]
        if not had_platform:
            os.environ.pop("PYOPENGL_PLATFORM", None)
