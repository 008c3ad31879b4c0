"""Health checks, energies and blow-up reports.

Inside ``jit`` nothing raises: the rollout carries an (O,) int32 status code per object. After
the run, outside ``jit``, :func:`first_failure` finds the first failing frame, and
``jaxplush.simulate`` turns it into a :class:`jaxplush.errors.SimulationError` naming step, object
and cause.

A soft-soft contact candidate list that overflows its capacity (:mod:`jaxplush.model.contact`) is a code
of its own, CONTACT_OVERFLOW, not a NaN: the contact force then uses the candidates that fit (the
step is inexact, and the code says so), and ``jaxplush.simulate`` and ``fitting.fit`` read it and
rerun with a larger capacity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.model import forces as model
from jaxplush.types import VOLUME_EPS

OK = 0
VOLUME_CLAMPED = 1   # warning: V < eps V0, the pressure clamp is active
NON_FINITE = 2       # error: a position became NaN or infinite
INVERTED = 3         # error: the enclosed volume became zero or negative
CONTACT_OVERFLOW = 4  # error: soft-soft contact candidates overflowed their capacity (steps inexact)
ERROR = NON_FINITE   # codes >= ERROR are failures

MESSAGES = {
    OK: "ok",
    VOLUME_CLAMPED: f"volume fell below {VOLUME_EPS:g} of its rest volume (pressure clamp active)",
    NON_FINITE: "positions became non-finite (NaN or infinite)",
    INVERTED: "the enclosed volume became zero or negative (the mesh turned inside out)",
    CONTACT_OVERFLOW: ("soft-soft contact candidates overflowed their capacity, so the contact forces were "
                       "incomplete (raise the scene keyword 'contact_capacity')"),
}


def object_status(topo, terms, x):
    """(O,) int32 status code of every object at positions x (V, 3)."""
    return status_codes(topo, terms, x.T)


def status_codes(topo, terms, xs):
    """(O, ...) int32 status codes at component-major positions ``xs``: three (V, ...) arrays, say
    a (3, V) array, or the batched engine's three (V, B) (codes (O, B), one per point)."""
    finite = jnp.isfinite(xs[0]) & jnp.isfinite(xs[1]) & jnp.isfinite(xs[2])
    count = jnp.asarray(topo.count, jnp.int32).reshape((-1,) + (1,) * (finite.ndim - 1))
    finite = model.per_object_sum(topo, finite.astype(jnp.int32)) == count
    code = jnp.where(finite, OK, NON_FINITE)
    if terms.gas:
        vol = model.object_face_volumes(topo, xs)
        v0 = jnp.asarray(topo.rest_volume, vol.dtype).reshape(count.shape)
        code = jnp.where(finite & (vol <= 0), INVERTED, code)
        code = jnp.where(finite & (vol > 0) & (vol < VOLUME_EPS * v0), VOLUME_CLAMPED, code)
    return code.astype(jnp.int32)


def with_overflow(code, overflow):
    """(O,) codes with CONTACT_OVERFLOW where ``overflow`` (O,) bool is set (it takes precedence:
    an inexact contact step may well be what made an object fail)."""
    return jnp.where(overflow, CONTACT_OVERFLOW, code).astype(jnp.int32)


def energy_terms(sim, params, state):
    """Energies (J) of a state as a dict of scalar arrays: kinetic, spring, gas, gravity, floor
    (the smooth floor's penalty) and total. Pure and traceable (:func:`energies` compiles it).

    The velocity at the state's time comes from ``sim.velocity_fn`` (for Verlet's half-step
    velocity u_n it is estimated to second order as v_n = u_n + a_n dt / 2).
    """
    topo = sim.topology
    x = state.x
    v = sim.velocity_fn(params, state)
    kin = model.kinetic_energy(topo, params, v)
    d = x[topo.edges[:, 0]] - x[topo.edges[:, 1]]
    l = jnp.sqrt(jnp.sum(d * d, axis=-1) + model.length_eps2(topo, x.dtype))
    spring = jnp.sum(0.5 * model.edge_stiffness(topo, params.k_structural) * (l - topo.rest_length) ** 2)
    zero = jnp.zeros((), x.dtype)
    gas = jnp.sum(model.gas_energy(topo, params, x, sim.scene.temperature)) if sim.terms.gas else zero
    height = jnp.matmul(x, jnp.asarray(sim.scene.gravity, x.dtype), precision=jax.lax.Precision.HIGHEST)
    grav = -jnp.sum(model.vertex_mass(topo, params) * height)
    floor = zero
    if sim.terms.floor_smooth:
        floor = model.smooth_floor_energy(topo, sim.terms.floor_smooth, params, x[:, 1])
    out = dict(kinetic=kin, spring=spring, gas=gas, gravity=grav, floor=floor)
    out["total"] = kin + spring + gas + grav + floor
    return out


def energies(sim, params, state):
    """Energies (J) of a state: dict of kinetic, spring, gas, gravity, floor (the smooth floor's
    penalty) and total (floats); :func:`energy_terms`, compiled once per program."""
    import functools
    fn = compiled.get(sim, "energies", lambda: jax.jit(functools.partial(energy_terms, sim)))
    return {k: float(v) for k, v in fn(params, state).items()}


def first_failure(codes_by_frame):
    """From (T, O) codes, the first (frame, object, code) with code >= ERROR, or None."""
    codes = np.asarray(codes_by_frame)
    bad = codes >= ERROR
    if not bad.any():
        return None
    t = int(np.argmax(bad.any(axis=1)))
    o = int(np.argmax(bad[t]))
    return t, o, int(codes[t, o])
