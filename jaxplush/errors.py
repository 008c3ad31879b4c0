"""Exceptions and warning categories of jaxplush.

Every error a user can cause derives from :class:`JaxplushError`; the CLI prints
its message (no traceback) and exits non-zero. Errors carry their fields (a path and line, a
step and object), so code that adds to one builds it from those, never from its text.

Every warning jaxplush issues is a :class:`JaxplushWarning` (a ``UserWarning``) of one of the
categories below, so a caller filters or matches them by category:

>>> import warnings
>>> from jaxplush.errors import ContactCapacityWarning, JaxplushWarning
>>> issubclass(ContactCapacityWarning, JaxplushWarning) and issubclass(JaxplushWarning, UserWarning)
True
>>> with warnings.catch_warnings():
...     warnings.filterwarnings("ignore", category=ContactCapacityWarning)
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
    """A numerical blow-up found after a rollout: which step, which object, why.

    Carries ``step``, ``object`` (index), ``object_name``, ``reason`` and ``hint`` (what to try,
    or ""): code that adds to the error builds a new one from these fields, never from the text."""

    def __init__(self, step, obj, name, reason, hint=""):
        self.step = int(step)
        self.object = int(obj)
        self.object_name = name
        self.reason = reason
        self.hint = hint
        msg = f"simulation failed at step {self.step}, object {self.object} ({name!r}): {reason}"
        if hint:
            msg += f". {hint}"
        super().__init__(msg)


class JaxplushWarning(UserWarning):
    """Base class of every warning jaxplush issues."""


class TimeStepWarning(JaxplushWarning):
    """dt (or the substeps a run needed) at or above the explicit integrator's stability limit."""


class VolumeClampWarning(JaxplushWarning):
    """An object's enclosed volume came near zero and the gas pressure was clamped."""


class ContactCapacityWarning(JaxplushWarning):
    """Soft-soft contact candidates overflowed their capacity; the run was repeated with a larger one."""


class SceneWarning(JaxplushWarning):
    """Something in a scene file was ignored (for example vertices no face uses)."""


class SimulationWarning(JaxplushWarning):
    """Some runs of a batch failed (a blow-up): they are marked in the result, not raised."""


class BackendWarning(JaxplushWarning):
    """jax was set up in a way jaxplush cannot correct (for example imported and started first)."""


class GradientWarning(JaxplushWarning):
    """A gradient is taken by plain automatic differentiation where the fused adjoint does not apply."""


class Note(str):
    """A warning's text as a result keeps it (``FitResult.warnings``, ``Trajectory.notes``), with its
    ``category`` (a :class:`JaxplushWarning` subclass): a str, so it prints and compares as the text."""

    category = JaxplushWarning

    def __new__(cls, text, category=JaxplushWarning):
        note = super().__new__(cls, text)
        note.category = category
        return note

    def __reduce__(self):
        return (Note, (str(self), self.category))


def warn(text, category, stacklevel=1):
    """Issue warning ``text`` of ``category`` (``stacklevel`` as :func:`warnings.warn`'s, counted from
    the caller) and return it as a :class:`Note`."""
    import warnings
    warnings.warn(text, category, stacklevel=stacklevel + 1)
    return Note(text, category)


def driven_path_error(d, scene_path, reason):
    """The error for a :class:`jaxplush.scene.parse.DrivenPath` ``d`` whose values are out of
    range: a :class:`SceneError` naming the scene file and the line of its ``driven`` keyword, or,
    for a path from a target's ``controls`` (no line), a :class:`TrajectoryError` naming that file."""
    if d.line:
        return SceneError(scene_path, d.line, reason)
    return TrajectoryError(d.file, reason)
