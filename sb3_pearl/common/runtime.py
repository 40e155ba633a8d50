"""Process set-up done by ``import sb3_pearl``, before MuJoCo or gymnasium-robotics are imported.

- :func:`select_mujoco_gl`: on Linux without a display, MuJoCo renders offscreen (``rgb_array``, videos) only with
  ``MUJOCO_GL=egl`` or ``osmesa``; without one it fails with "an OpenGL platform library has not been loaded".
  When ``MUJOCO_GL`` is unset and there is no display, the first of EGL / OSMesa found is selected.
- :func:`drop_adroit_notice`: gymnasium-robotics prints, at import, a notice about the rewards of its Adroit hand
  envs (which this project does not use); that one message is removed from ``farama_notifications`` before the import.
"""

from __future__ import annotations

import ctypes.util
import os
import sys

# MuJoCo's offscreen backends, in order of preference, with the library each needs.
OFFSCREEN_BACKENDS = (("egl", "EGL"), ("osmesa", "OSMesa"))


def has_display() -> bool:
    """Whether windows can be opened: always off Linux, else when ``DISPLAY`` or ``WAYLAND_DISPLAY`` is set."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def select_mujoco_gl() -> str | None:
    """
    Set ``MUJOCO_GL`` to an offscreen backend found on this machine when it is unset and there is no display.

    Does nothing once MuJoCo is imported (the variable is read at import) or when the user chose a backend.

    :return: the backend set (None: nothing changed)
    """
    if "MUJOCO_GL" in os.environ or has_display() or "mujoco" in sys.modules:
        return None
    for backend, library in OFFSCREEN_BACKENDS:
        if ctypes.util.find_library(library):
            os.environ["MUJOCO_GL"] = backend
            return backend
    return None


def drop_adroit_notice() -> None:
    """Remove gymnasium-robotics' Adroit reward notice (printed to stderr when it is imported) from farama_notifications."""
    try:
        from farama_notifications import notifications
    except ImportError:  # pragma: no cover - a dependency of gymnasium
        return
    robotics = notifications.get("gymnasium_robotics")
    if isinstance(robotics, dict):
        for version, message in list(robotics.items()):
            if isinstance(message, str) and message.startswith("AdroitHand"):
                del robotics[version]


__all__ = ["OFFSCREEN_BACKENDS", "drop_adroit_notice", "has_display", "select_mujoco_gl"]
