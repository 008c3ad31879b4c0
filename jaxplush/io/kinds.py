"""The kinds of target: one protocol, :class:`Kind`, and the four kinds jaxplush reads from files.

A target (:class:`jaxplush.fitting.targets.Target`) is of one kind. The built-in ones
(``TargetKind.POSITIONS`` and so on; ``TargetKind`` is :class:`Kind`):

* ``positions``: every vertex of the scene at every frame (a simulation's output);
* ``points``: a point cloud per frame, no correspondence to the vertices (a scan; frames may hold
  different numbers of points, padded with NaN rows);
* ``tracks``: points tracked on the surface, each at a vertex or a fixed spot of a face (NaN rows:
  not seen in that frame);
* ``mixed``: ``points`` and ``tracks`` together, on the same frames.

A kind is a class: it says what it is (its datasets, residual components, whether it observes
every vertex, material points, which rows hold an observation, its words in messages) and it
owns what the fit needs of it (:meth:`Kind.residual`, :meth:`Kind.mean_sq`,
:meth:`Kind.residual_vertices`, :meth:`Kind.linearised`). Code elsewhere asks the kind instead of
comparing its name, so a new kind is one subclass, in one file, wherever it lives (the tests fit
silhouettes, 2-D outlines, defined outside the package). Kinds are strings equal to their
names (``TargetKind.POSITIONS == "positions"``), as the HDF5 files, FIT.h5 and the command line
spell them; ``Kind("positions")`` is the one instance of a kind of that name.

The geometry of the built-in kinds' residuals is in :mod:`jaxplush.io.observe` (JAX code the
viewer, which reads targets too, does not load), reached from here on first use.
"""

from __future__ import annotations

import numpy as np

from jaxplush.types import ShowsValue

#: name -> the one instance of every kind defined (built-in or a user's subclass).
_KINDS = {}


class Kind(ShowsValue, str):
    """A kind of target (module docstring): a subclass sets :attr:`name` and the attributes that
    differ from these defaults, and implements :meth:`residual` (the rest has defaults).

    Attributes (class attributes):
      name: its name (the instance is a str equal to it).
      datasets: the HDF5 datasets holding its frames.
      components: residual entries per observation (3 for a vertex's or a track's x, y, z; 1 for a
        distance): the normaliser of a known noise sigma is ``components`` sigma².
      every_vertex: it observes every vertex at every frame (node states for multiple shooting, the
        force balance of the linear start).
      material_points: each observation is a known material point (a vertex, a spot of a face).
      tracked: it holds tracks. compound: it is made of parts of other kinds (``Target.parts``).
      padded: its rows may be NaN (padding, not seen). sees_vertices: some observation is a vertex
        or a spot of a face.
      unit, adjective, noun, shape_text: its words in messages.
    """

    name = None
    datasets = ()
    components = 1
    every_vertex = False
    material_points = False
    tracked = False
    compound = False
    padded = True
    sees_vertices = False
    unit = "observation"
    adjective = "custom"
    noun = "observations"
    shape_text = "[T, M, D]"

    def __new__(cls, name=None):
        if cls is Kind:                                   # Kind("positions"): the kind of that name
            if isinstance(name, Kind):
                return name
            try:
                return _KINDS[str(name)]
            except KeyError:
                raise ValueError(f"unknown target kind {name!r}; expected one of "
                                 f"{', '.join(repr(str(k)) for k in KINDS)}") from None
        if cls.name is None:
            raise TypeError(f"{cls.__name__} sets no name")
        own = _KINDS.get(cls.name)
        if type(own) is cls:
            return own
        if own is not None and own in KINDS:
            raise TypeError(f"{cls.__name__}: the target kind {cls.name!r} is built in; give yours another name")
        self = str.__new__(cls, cls.name)
        _KINDS[cls.name] = self
        return self

    @property
    def value(self):
        """Its name, as a plain str."""
        return str.__str__(self)

    def __reduce__(self):                 # pickled by name: the one instance comes back
        return (Kind, (self.value,))

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self

    def observed(self, data):
        """(T, N) bool: the rows of frames ``data`` (T, N, D) that hold an observation (the finite
        rows; every row of a kind that is not :attr:`padded`)."""
        data = np.asarray(data)
        return np.isfinite(data).all(axis=2) if self.padded else np.ones(data.shape[:2], bool)

    # ---- what the fit needs of a kind -------------------------------------------------------

    def residual(self, target, topology, scale2, normalisation):
        """``(frame_fn, per_frame, near_fn)``: the kind's residuals.

        ``frame_fn(frames (C, V, 3), data (C, M, D)) -> (C * per_frame,)``: the residuals (m, before
        the loss's normalisation) of C simulated frames against their observations, JAX-traceable
        and pure (the fit vmaps it over a batch of parameter points, and over chunks of frames).
        Rows that hold no observation give residuals 0. ``near_fn``: None, or ``(frames, data) ->
        (C * per_frame,)`` int32, the vertex each residual is measured from when that depends on
        the frames (a scan's nearest vertex). ``scale2`` and ``normalisation`` are the loss's
        normaliser (a kind may correct for a known noise with them)."""
        raise NotImplementedError(f"the target kind {self.value!r} defines no residual")

    def mean_sq(self, target, topology):
        """``(x (V, 3), y (M, D)) -> d_j``: one frame's mean squared distance (m²), the loss's term
        (and, at the rest shape, its motion scale). The sum of its squared residuals times T / N
        (N observations over T frames: every observation weighs alike) by default."""
        frame_fn, _, _ = self.residual(target, topology, 0.0, "motion")
        observed = self.observed(target.data)
        if not observed.any():
            raise ValueError(f"{target.path}: the target's frames hold no observation")
        weight = len(observed) / float(observed.sum())

        def mean_sq(x, y):
            r = frame_fn(x[None], y[None])
            return (r @ r) * weight
        return mean_sq

    def residual_vertices(self, target, topology, frames=None):
        """(n,) int64 or None: the vertex each residual of the whole target (T frames, laid out as
        :meth:`residual` lays them) is measured from, which says its object; -1 for a residual of no
        one vertex. ``frames`` (T, V, 3): simulated frames at the target's steps, for kinds whose
        rows find their vertex by position. Default None: unknown (the fit then scores every
        object by the whole loss)."""
        return None

    def linearised(self, target, topology, loss, frames, jac):
        """(residual (n,), jac (n, P)) for the identifiability report: the residuals (m) at
        ``frames`` (T, V, 3) and their Jacobian, from the frames' Jacobian ``jac`` (T V 3, P).
        Default: :meth:`residual` and its forward-mode derivative (float64)."""
        import jax
        import jax.numpy as jnp
        frame_fn, _, _ = self.residual(target, topology, loss.scale2, loss.normalisation)
        with jax.enable_x64(True):
            x = jnp.asarray(frames, jnp.float64)
            y = jnp.asarray(target.data, jnp.float64)
            jac = jnp.asarray(jac, jnp.float64).reshape(x.shape + (-1,))
            r, lin = jax.linearize(lambda f: frame_fn(f, y), x)
            cols = jax.vmap(lin, in_axes=-1, out_axes=-1)(jac)
            return np.asarray(r, np.float64), np.asarray(cols, np.float64)


def row_weight(target, always=False):
    """T / N for a target's rows with NaN padding or rows not seen (N observed over T frames: every
    observation weighs alike in a frame's sum), None where every row is observed (unless
    ``always``: a tracks target's distance is always a sum over its tracks)."""
    kind = Kind(target.kind)
    if kind.compound:
        raise ValueError("a mixed target's terms are weighed each on its own (Target.parts)")
    observed = kind.observed(target.data)
    if not always and observed.all():
        return None
    if not observed.any():
        raise ValueError(f"{target.path}: the target's frames hold no observation")
    return len(observed) / float(observed.sum())


def _observe():
    from jaxplush.io import observe
    return observe


class Positions(Kind):
    """Every vertex of the scene at every frame, (T, V, 3)."""

    name = "positions"
    datasets = ("positions",)
    components = 3
    every_vertex = True
    material_points = True
    padded = False
    sees_vertices = True
    unit = "vertex"
    adjective = "position"
    noun = "vertex positions"
    shape_text = "[T, V, 3]"

    def residual(self, target, topology, scale2, normalisation):
        return _observe().vertex_residual(target)

    def mean_sq(self, target, topology):
        return _observe().squared_distance

    def residual_vertices(self, target, topology, frames=None):
        v = np.shape(target.data)[1]
        return np.tile(np.repeat(np.arange(v, dtype=np.int64), 3), target.n_frames)

    def linearised(self, target, topology, loss, frames, jac):
        return (np.asarray(frames, np.float64) - np.asarray(target.data, np.float64)).reshape(-1), jac


class Points(Kind):
    """A point cloud per frame, (T, M, 3) with NaN rows of padding: no correspondence to the vertices."""

    name = "points"
    datasets = ("points",)
    unit = "point"
    adjective = "point-cloud"
    noun = "point clouds"
    shape_text = "[T, M, 3]"

    def residual(self, target, topology, scale2, normalisation):
        return _observe().surface_residual(target, topology, scale2, normalisation)

    def mean_sq(self, target, topology):
        losses = _observe()
        return losses.point_surface(topology.faces, topology.n_vertices, row_weight(target))

    def residual_vertices(self, target, topology, frames=None):
        if frames is None:
            raise ValueError("a point-cloud target needs simulated frames to assign its points to vertices")
        return np.concatenate([_observe().nearest_vertex(x, p) for x, p in
                               zip(np.asarray(frames, np.float64), np.asarray(target.data, np.float64))])

    def linearised(self, target, topology, loss, frames, jac):
        return _observe().nearest_point_residual(frames, target.data), jac


class Tracks(Kind):
    """Points tracked on the surface, (T, M, 3), each a vertex or a fixed spot of a face (NaN rows:
    not seen)."""

    name = "tracks"
    datasets = ("tracks",)
    components = 3
    material_points = True
    tracked = True
    sees_vertices = True
    unit = "track"
    adjective = "tracks"
    noun = "tracked points"
    shape_text = "[T, M, 3]"

    def residual(self, target, topology, scale2, normalisation):
        return _observe().track_residual(target)

    def mean_sq(self, target, topology):
        losses = _observe()
        return losses.track_distance2(target.track_vertices, target.track_weights, row_weight(target, always=True))

    def residual_vertices(self, target, topology, frames=None):
        first = np.asarray(target.track_vertices, np.int64)[:, 0]
        return np.tile(np.repeat(first, 3), target.n_frames)

    def linearised(self, target, topology, loss, frames, jac):
        return _observe().track_linearised(target, frames, jac)


class Mixed(Kind):
    """A scan and tracks on the same frames (``Target.parts``: its points, then its tracks)."""

    name = "mixed"
    datasets = ("points", "tracks")
    tracked = True
    compound = True
    sees_vertices = True
    unit = "point or track"
    adjective = "scan-and-tracks"
    noun = "a scan with tracked points"
    shape_text = "[T, M, 3]"

    def residual(self, target, topology, scale2, normalisation):
        raise ValueError("a mixed target's residuals are its parts' (jaxplush.fitting.objective.losses.make_residual)")

    def mean_sq(self, target, topology):
        raise ValueError("a mixed target's terms are weighed each on its own (Target.parts)")

    def residual_vertices(self, target, topology, frames=None):
        # per frame, its points' rows then its tracks' (as its residuals are laid out)
        rows = [Kind(p.kind).residual_vertices(p, topology, frames).reshape(target.n_frames, -1)
                for p in target.parts]
        return np.concatenate(rows, axis=1).ravel()

    def linearised(self, target, topology, loss, frames, jac):
        return _observe().mixed_linearised(target, loss, frames, jac)


#: Every built-in kind, in the order :func:`jaxplush.fitting.targets.load_target` prefers them when
#: a file holds several (a file's ``points`` and ``tracks`` together are a mixed target).
KINDS = (Positions(), Mixed(), Points(), Tracks())

#: The built-in kinds by attribute (``TargetKind.POSITIONS``); ``TargetKind(name)`` finds any kind.
TargetKind = Kind
Kind.POSITIONS, Kind.MIXED, Kind.POINTS, Kind.TRACKS = KINDS


def kind(name):
    """The kind named ``name`` (a str or a kind); ValueError for any other."""
    return Kind(name)
