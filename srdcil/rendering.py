"""Headless OpenGL for MuJoCo rendering, chosen where rendering starts (never at import).

Without a display, MuJoCo's default GL backend (glfw) cannot render. :func:`headless_gl`, called by
the renderers of srdcil's envs before their first frame, keeps an explicit ``MUJOCO_GL`` (or a
display) as it is; otherwise it tries EGL, then OSMesa, and points MuJoCo's renderer at the first
whose context can be created. It answers whether rendering works here (cached); it never raises.
"""
from __future__ import annotations

import ctypes.util
import importlib
import os
import sys
from typing import Optional

__all__ = ["headless_gl"]

_CHOICE: Optional[str] = None
_DONE = False


def headless_gl() -> Optional[str]:
    """The GL backend MuJoCo renders with here (``"egl"``, ``"osmesa"``, or ``MUJOCO_GL`` / ``"glfw"``
    with a display), or None when none works."""
    global _CHOICE, _DONE
    if _DONE:
        return _CHOICE
    _DONE = True
    if os.environ.get("MUJOCO_GL") or os.environ.get("DISPLAY"):
        _CHOICE = os.environ.get("MUJOCO_GL") or "glfw"
        return _CHOICE
    import mujoco.rendering.classic.gl_context as gl_context

    for backend, lib in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(lib) is None:
            continue
        if "OpenGL" not in sys.modules:  # PyOpenGL reads its platform at import
            os.environ.setdefault("PYOPENGL_PLATFORM", backend)
        try:
            context_class = importlib.import_module(f"mujoco.{backend}").GLContext
            ctx = context_class(8, 8)
            ctx.make_current()
            ctx.free()
        except Exception:  # noqa: BLE001 - this backend cannot create a context here: try the next
            continue
        gl_context.GLContext = context_class
        _CHOICE = backend
        return _CHOICE
    return None
