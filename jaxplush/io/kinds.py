"""The kinds of target, and what each one is: the one place that names them (the viewer of the
core and the fit, through :mod:`jaxplush.fitting.kinds`, read them from here).

A target (:class:`jaxplush.fitting.targets.Target`) is one of four kinds, :class:`TargetKind`:

* ``positions``: every vertex of the scene at every frame (a simulation's output);
* ``points``: a point cloud per frame, no correspondence to the vertices (a scan; frames may hold
  different numbers of points, padded with NaN rows);
* ``tracks``: points tracked on the surface, each at a vertex or a fixed spot of a face (NaN rows:
  not seen in that frame);
* ``mixed``: ``points`` and ``tracks`` together, on the same frames.

Code elsewhere asks a kind what it needs to know (its datasets, residual components, whether it
observes every vertex or material points at all, which rows hold an observation) instead of
comparing the kind's name: a new kind is a member here with its answers. ``TargetKind`` members
are strings equal to their names (``TargetKind.POSITIONS == "positions"``), as the HDF5 files,
FIT.h5 and the command line spell them.
"""

from __future__ import annotations

import numpy as np

from jaxplush.types import StrEnum


class TargetKind(StrEnum):
    """The kind of a target (module docstring); equal to, hashed and printed as its name."""

    POSITIONS = "positions"
    POINTS = "points"
    TRACKS = "tracks"
    MIXED = "mixed"

    @property
    def datasets(self):
        """The HDF5 datasets that hold its frames (a mixed target's: points, then tracks)."""
        return ("points", "tracks") if self is TargetKind.MIXED else (self.value,)

    @property
    def components(self):
        """Residual entries per observation: 3 (x, y, z) for a vertex or a track, 1 (a distance to
        the surface) for a point; a mixed target's normaliser is per point distance."""
        return 3 if self in (TargetKind.POSITIONS, TargetKind.TRACKS) else 1

    @property
    def every_vertex(self):
        """Whether it observes every vertex at every frame: node states for multiple shooting, the
        force balance of the linear start, a residual per vertex."""
        return self is TargetKind.POSITIONS

    @property
    def material_points(self):
        """Whether each observation is a known material point (a vertex, or a spot of a face): the
        residuals split by object, the loss floor per coordinate."""
        return self in (TargetKind.POSITIONS, TargetKind.TRACKS)

    @property
    def tracked(self):
        """Whether it holds tracks (tracks, or mixed)."""
        return self in (TargetKind.TRACKS, TargetKind.MIXED)

    @property
    def compound(self):
        """Whether it is made of parts of other kinds (mixed: points and tracks)."""
        return self is TargetKind.MIXED

    @property
    def padded(self):
        """Whether its rows may be NaN: padding of a point cloud, a track not seen in a frame."""
        return self is not TargetKind.POSITIONS

    @property
    def unit(self):
        """One observation, in a message: "vertex", "point", "track" or "point or track"."""
        return {"positions": "vertex", "points": "point", "tracks": "track", "mixed": "point or track"}[self.value]

    @property
    def adjective(self):
        """The target in a phrase: "position", "point-cloud", "tracks" or "scan-and-tracks"."""
        return {"positions": "position", "points": "point-cloud", "tracks": "tracks",
                "mixed": "scan-and-tracks"}[self.value]

    @property
    def noun(self):
        """What the target is, in a phrase."""
        return {"positions": "vertex positions", "points": "point clouds", "tracks": "tracked points",
                "mixed": "a scan with tracked points"}[self.value]

    @property
    def sees_vertices(self):
        """Whether any of its observations is a vertex or a spot of a face (all but a scan alone)."""
        return self is not TargetKind.POINTS

    @property
    def shape_text(self):
        """The shape its frames have, in a message."""
        return "[T, V, 3]" if self is TargetKind.POSITIONS else "[T, M, 3]"

    def observed(self, data):
        """(T, N) bool: the rows of frames ``data`` (T, N, 3) that hold an observation (every vertex
        of a positions target; the finite rows of the others)."""
        data = np.asarray(data)
        return np.isfinite(data).all(axis=2) if self.padded else np.ones(data.shape[:2], bool)


#: Every kind, in the order :func:`jaxplush.fitting.targets.load_target` prefers them when a file
#: holds several (a file's ``points`` and ``tracks`` together are a mixed target).
KINDS = (TargetKind.POSITIONS, TargetKind.MIXED, TargetKind.POINTS, TargetKind.TRACKS)


def kind(name):
    """The :class:`TargetKind` named ``name`` (a str or a kind); ValueError for any other."""
    try:
        return TargetKind(name)
    except ValueError:
        raise ValueError(f"unknown target kind {name!r}; expected one of "
                         f"{', '.join(repr(k.value) for k in KINDS)}") from None
