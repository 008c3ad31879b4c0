"""Core data types and shape conventions.

Shape letters used in every docstring:
  V  vertices (all objects, concatenated object by object)
  E  unique edges (springs)
  F  triangle faces
  O  objects
  K  one-ring width (largest vertex valence)
  T  saved frames

Three kinds of data, kept apart on purpose:
  * ``Params``: per-object physical parameters, a pytree of (O,) arrays that gradients and
    ``vmap`` flow into (``k_structural`` may instead be an (E,) per-edge field).
  * ``State``: the integrator's carry (positions and a velocity).
  * topology (:class:`jaxplush.model.forces.Topology`): numpy index tables closed over by the
    compiled step, never traced.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np

#: Universal gas constant, J/(mol K).
GAS_CONSTANT = 8.314

#: Volume clamp: pressure uses max(V, VOLUME_EPS * V0) (docs/model.md §1), a C¹ continuation of
#: -nRT ln V that keeps the force conservative and finite as V -> 0.
VOLUME_EPS = 0.05

PARAM_NAMES = ("k_structural", "damping", "dashpot", "drag", "nmol", "total_weight")


class Params(NamedTuple):
    """Per-object physical parameters, each an (O,) array (k_structural: or (E,)).

    Attributes:
      k_structural: (O,) spring stiffness of every edge of each object, N/m; or (E,) a per-edge
        stiffness field, in the order of the topology's ``edges`` (the scene's sorted unique edges;
        scene keywords ``k_region``/``k_edge``). The shape decides, statically
        (:mod:`jaxplush.model.layout`).
      damping: (O,) the report's Verlet damping D; the per-step factor is f = 1/D, and
        D = 0 means no damping. Depends on dt (docs/model.md §5); prefer ``dashpot``/``drag``.
      dashpot: (O,) edge dashpot coefficient c, N s/m: f_i = -c ((v_i - v_j).d) d.
      drag: (O,) mass-proportional air drag gamma, 1/s: f_i = -gamma m_i v_i.
      nmol: (O,) moles of ideal gas inside (0: no gas).
      total_weight: (O,) object mass, kg, split evenly over its vertices.
    """

    k_structural: object
    damping: object
    dashpot: object
    drag: object
    nmol: object
    total_weight: object

    def as_numpy(self):
        return Params(*(np.asarray(p) for p in self))


class State(NamedTuple):
    """Integrator state.

    Attributes:
      x: (V, 3) vertex positions, m.
      v: (V, 3) velocities, m/s. For the Verlet integrator this is the backward difference
        (x_n - x_{n-1}) / dt, i.e. the velocity at the half step n - 1/2.
    """

    x: object
    v: object


class ShowsValue:
    """For a str subclass with a ``value``: prints, formats, shows (repr) and hashes as that value,
    so plain strings, dict keys, f-strings, JSON and HDF5 attributes see the text (a fit's status,
    a target's kind)."""

    def __str__(self):
        return self.value

    def __repr__(self):
        return repr(self.value)

    def __format__(self, spec):
        return format(self.value, spec)

    def __hash__(self):
        return str.__hash__(self)


class StrEnum(ShowsValue, str, enum.Enum):
    """A str-valued enum that compares, hashes, prints, formats and shows as its value
    (:class:`ShowsValue`)."""
