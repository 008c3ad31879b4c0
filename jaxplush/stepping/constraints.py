"""Position-level constraints applied after every integrator update: the floor and pinned vertices.

``make_constrain(topo, terms, scene, dt)`` returns ``constrain(x_old, x_new, v_new) -> (x, v)`` on
component-major (3, V) arrays, where ``v_new`` is the velocity the integrator carries
(``(x_new - x_old) / dt`` for Verlet's half-step velocity and the Euler-type schemes). Every
integrator calls it once per step, so floor response and pins live in one place.

Floor (y >= H): a projection that sets the vertex's vertical velocity to the one that lands it
on the floor; it only ever removes energy (docs/model.md §6). Pinned vertices keep their rest
position with zero velocity. Driven vertices (scene keyword ``driven``, :class:`Drive`) are set
last, from their path: the path wins over the floor and every force (docs/model.md §10).

Optional floor response (scene keywords; absent = the plain projection above, not traced):

* ``floor_restitution E``: a vertex that hits the floor faster than v_rest = 2 |g_y| dt (Jolt's
  threshold, so resting vertices do not jitter) leaves it with E times its incoming normal speed.
  The switch is a sigmoid of width v_rest / 2 in the impact speed, so the response is smooth.
* ``floor_friction MU``: Coulomb friction in the projection (Jolt-style, docs/model.md §6). The
  projection changes a contacting vertex's normal velocity by dv_n >= 0; its tangential
  velocity v_t then loses at most MU dv_n: v_t <- v_t max(0, 1 - MU dv_n / sqrt(|v_t|² + eps²)),
  eps = 1e-3 v_rest, and its tangential displacement this step is reduced to match. A vertex at
  rest sticks while |g_t| < MU |g_n| (the friction angle) and slides otherwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.errors import driven_path_error


def landing_velocity(y_old, height, h):
    """The floor projection's vertical velocity (H - y_old) / h: the one that lands a vertex that
    starts the step at height y_old exactly on the floor H after a step of h. Every engine's
    projection (this module's hook, the batched engine's written-out plain floor) uses it; the
    fused adjoint's floor mask is its transpose (d/dy_old = -1/h)."""
    return (height - y_old) / h


#: The last step number a run can reach (the step counter is int32): a release time at or beyond
#: MAX_STEPS steps is refused, since no run could ever reach it.
MAX_STEPS = int(np.iinfo(np.int32).max) - 1


def release_step(d, h, scene_path="<scene>"):
    """The first substep (of length ``h``) in which the vertices of driven path ``d`` are free:
    floor(until / h), decided in integers (k + 1 <= T / h). A release time so late that no run's
    step counter reaches it raises a :class:`jaxplush.errors.JaxplushError` (a
    :class:`~jaxplush.errors.SceneError` naming the scene line, or a
    :class:`~jaxplush.errors.TrajectoryError` naming the target's ``controls/until``)."""
    steps = float(d.until) / float(h) * (1 + 1e-12)
    if not (np.isfinite(steps) and steps < MAX_STEPS):
        what = f"'driven' release time 'until {d.until:g}'" if d.line else f"attribute 'controls/until' = {d.until:g}"
        raise driven_path_error(
            d, scene_path,
            f"{what} s is {steps:.3g} steps of {h:g} s, beyond any run (at most {MAX_STEPS} steps); leave it out "
            "to drive the vertices throughout the run")
    return int(np.floor(steps))


def check_path_speed(d, scene_path="<scene>"):
    """Refuse a driven path whose speed between two samples is not a finite float64 (samples
    5e-324 s apart, or positions 1e308 m apart): the vertex would leave with an infinite velocity."""
    times = np.asarray(d.times, np.float64)
    if len(times) < 2:
        return
    with np.errstate(all="ignore"):
        speed = np.diff(np.asarray(d.positions, np.float64), axis=0) / np.diff(times)[:, None, None]
    bad = ~np.isfinite(speed).all(axis=(1, 2))
    if bad.any():
        i = int(np.argmax(bad))
        what = f"'driven' path file {d.source!r}" if d.line else "dataset 'controls/positions'"
        raise driven_path_error(
            d, scene_path,
            f"{what}: the speed between samples {i} and {i + 1} (t = {times[i]:g} and {times[i + 1]:g} s) "
            "overflows: space the samples further apart in time, or move the path less")


class Drive:
    """The driven vertices of a scene (``scene.driven``) as constants of a step of length ``h``
    (docs/model.md §10). Substep k advances t_k = k h to t_{k+1} = (k + 1) h; a path is linear
    between its samples (``jnp.interp`` per coordinate) and holds its first and last sample
    outside them. A vertex with a release time T (``until T``) is driven in the substeps that end
    at or before T (k + 1 <= T / h, decided in integers) and free afterwards.

    Attributes:
      index: (D,) int32 driven vertices, in the order of ``scene.driven``.
      release: (D,) int64 first substep in which each is free (None: none is ever released).
    """

    def __init__(self, scene, h):
        self.h = float(h)
        self.groups = []
        release = []
        for d in scene.driven:
            pos = np.ascontiguousarray(np.transpose(d.positions, (2, 1, 0)))     # (3, Dg, S)
            self.groups.append((np.asarray(d.times, np.float64), pos))
            r = np.iinfo(np.int32).max if d.until is None else release_step(d, self.h, scene.path)
            release += [r] * len(d.vertices)
            check_path_speed(d, scene.path)
        self.index = np.asarray(scene.driven_vertices, np.int32)
        self.release = np.asarray(release, np.int64) if any(d.until is not None for d in scene.driven) else None
        # at t = 0 (numpy): positions and the path's velocity, the slope of the interpolant from the right
        p0, s0 = [], []
        for times, pos in self.groups:
            p0.append(np.stack([[np.interp(0.0, times, pos[c, j]) for j in range(pos.shape[1])] for c in range(3)]))
            i = int(np.searchsorted(times, 0.0, side="right")) - 1
            if 0 <= i < len(times) - 1:
                s0.append((pos[:, :, i + 1] - pos[:, :, i]) / (times[i + 1] - times[i]))
            else:
                s0.append(np.zeros((3, pos.shape[1])))
        self.x_start = np.concatenate(p0, axis=1)
        self.v_start = np.concatenate(s0, axis=1)

    def position(self, t, dtype):
        """(3, D) positions at the (traced) time ``t``; (3, D) + t.shape for an array of times (one
        per batch lane)."""
        out = []
        t = jnp.asarray(t, dtype)
        for times, pos in self.groups:
            if len(times) == 1:
                p = pos[:, :, 0].reshape(pos.shape[:2] + (1,) * t.ndim)
                out.append(jnp.broadcast_to(jnp.asarray(p, dtype), pos.shape[:2] + t.shape))
                continue
            tt, pp = jnp.asarray(times, dtype), jnp.asarray(pos, dtype)
            out.append(jax.vmap(jax.vmap(lambda fp: jnp.interp(t, tt, fp)))(pp))
        return out[0] if len(out) == 1 else jnp.concatenate(out, axis=1)

    def active(self, k):
        """(D,) bool: driven in substep ``k`` (None: all are, always). ``k`` may also be an array
        of substep indices (one per batch lane, the batched engine): then (D,) + k.shape."""
        if self.release is None:
            return None
        if k is None:
            raise missing_step_error()
        k = jnp.asarray(k, jnp.int32)
        release = np.minimum(self.release, np.iinfo(np.int32).max).reshape((-1,) + (1,) * k.ndim)
        return k[None] < jnp.asarray(release, jnp.int32)

    def apply(self, x, v, k):
        """(x, v) with the driven vertices at their path's position at the end of substep ``k``
        and its velocity over the substep, (p(t_{k+1}) - p(t_k)) / h (released ones untouched)."""
        if k is None:
            raise missing_step_error()
        with jax.named_scope("driven"):
            k = jnp.asarray(k, jnp.int32)
            t0 = k.astype(x.dtype) * self.h
            t1 = (k + 1).astype(x.dtype) * self.h
            p0, p1 = self.position(t0, x.dtype), self.position(t1, x.dtype)
            vel = (p1 - p0) * (1.0 / self.h)
            idx = self.index
            act = self.active(k)
            if act is not None:
                p1 = jnp.where(act, p1, x[:, idx])
                vel = jnp.where(act, vel, v[:, idx])
            return x.at[:, idx].set(p1), v.at[:, idx].set(vel)

    def hold(self, a, k):
        """``a`` (3, V) with zeros at the vertices driven in substep ``k`` (their acceleration or
        velocity change inside a scheme's stages, as for pinned vertices)."""
        act = self.active(k)
        idx = self.index
        if act is None:
            return a.at[:, idx].set(0.0)
        return a.at[:, idx].set(jnp.where(act, 0.0, a[:, idx]))

    def free(self, k, n_vertices, dtype):
        """(V,) 1 for vertices not driven in substep ``k``, 0 for driven ones."""
        base = np.ones(n_vertices)
        if self.release is None:
            base[self.index] = 0.0
            return jnp.asarray(base, dtype)
        act = self.active(k)
        return jnp.asarray(base, dtype).at[self.index].set(jnp.where(act, 0.0, 1.0).astype(dtype))

    def start(self, x, v):
        """(x, v) at t = 0: the driven vertices at their path's first position with its velocity."""
        idx = self.index
        return (x.at[:, idx].set(jnp.asarray(self.x_start, x.dtype)),
                v.at[:, idx].set(jnp.asarray(self.v_start, v.dtype)))


def missing_step_error():
    return ValueError("this scene has driven vertices (keyword 'driven'), whose positions depend on time: "
                      "pass the index of the step being advanced, step_fn(params, state, step=n) "
                      "(the state is at t = n dt)")


def make_constrain(topo, terms, scene, dt, drive=None):
    """Build ``constrain(x_old, x_new, v_new, k=None) -> (x, v)`` for a scene (only needed parts
    traced); ``k``, the substep index, is needed (and read) only with driven vertices
    (``drive``: a :class:`Drive` of the scene for steps of ``dt``; built here if None)."""
    fixed = topo.fixed
    if getattr(terms, "driven", False) and drive is None:
        drive = Drive(scene, dt)
    floor = scene.floor
    x0_soa = np.ascontiguousarray(topo.x0.T)
    mu = float(terms.floor_friction)
    restitution = float(terms.floor_restitution)
    # (dt may be traced: the batched engine's step when its substep count is data)
    v_rest = 2.0 * abs(float(scene.gravity[1])) * dt
    v_rest = max(v_rest, 1e-9) if isinstance(v_rest, float) else jnp.maximum(v_rest, 1e-9)

    def constrain(x_old, x, v, k=None):
        if terms.floor:
            with jax.named_scope("floor"):
                below = x[1] < floor
                vy_in = v[1]
                vy = landing_velocity(x_old[1], floor, dt)
                if restitution:
                    with jax.named_scope("floor_restitution"):
                        speed = -vy_in
                        w = jax.nn.sigmoid((speed - v_rest) / (0.5 * v_rest))
                        vy = vy + w * (restitution * speed - vy)
                v = v.at[1].set(jnp.where(below, vy, vy_in))
                x = x.at[1].set(jnp.maximum(x[1], floor))
                if mu:
                    with jax.named_scope("floor_friction"):
                        dvn = jnp.maximum(vy - vy_in, 0.0)
                        vt2 = v[0] * v[0] + v[2] * v[2] + (1e-3 * v_rest) ** 2
                        keep = jnp.maximum(1.0 - mu * dvn * jax.lax.rsqrt(vt2), 0.0)
                        lose = jnp.where(below, 1.0 - keep, 0.0)       # fraction of v_t removed
                        for c in (0, 2):
                            x = x.at[c].add(-lose * v[c] * dt)
                            v = v.at[c].add(-lose * v[c])
        if terms.fixed:
            with jax.named_scope("fixed"):
                x = x.at[:, fixed].set(jnp.asarray(x0_soa[:, fixed], x.dtype))
                v = v.at[:, fixed].set(0.0)
        if getattr(terms, "driven", False):
            if k is None:
                raise missing_step_error()
            x, v = drive.apply(x, v, k)
        return x, v

    return constrain
