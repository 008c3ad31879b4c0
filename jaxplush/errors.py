"""Exceptions raised by jaxplush.

Every error a user can cause derives from :class:`JaxplushError`; the CLI prints
its message (no traceback) and exits non-zero.
"""

from __future__ import annotations


class JaxplushError(Exception):
    """Base class of all user-facing jaxplush errors."""


class SceneError(JaxplushError):
    """A malformed scene file: carries ``path``, ``line`` (1-based, or None) and ``reason``."""

    def __init__(self, path, line, reason):
        self.path = str(path)
        self.line = line
        self.reason = reason
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {reason}")


class TrajectoryError(JaxplushError):
    """A malformed or unreadable trajectory (HDF5) file."""

    def __init__(self, path, reason):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class SimulationError(JaxplushError):
    """A numerical blow-up found after a rollout: which step, which object, why."""

    def __init__(self, step, obj, name, reason, hint=""):
        self.step = int(step)
        self.object = int(obj)
        self.object_name = name
        self.reason = reason
        msg = f"simulation failed at step {self.step}, object {self.object} ({name!r}): {reason}"
        if hint:
            msg += f". {hint}"
        super().__init__(msg)


def driven_path_error(d, scene_path, reason):
    """The error for a :class:`jaxplush.scene.parse.DrivenPath` ``d`` whose values are out of
    range: a :class:`SceneError` naming the scene file and the line of its ``driven`` keyword, or,
    for a path from a target's ``controls`` (no line), a :class:`TrajectoryError` naming that file."""
    if d.line:
        return SceneError(scene_path, d.line, reason)
    return TrajectoryError(d.file, reason)
