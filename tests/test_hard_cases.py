"""Hard cases for every integrator (issue 4, docs/model.md §8 "Hard cases").

Each run either is stable (no NaN, every saved volume positive, total energy bounded by its
initial value plus a margin) or stops with a :class:`jaxplush.SimulationError` that names the
step, the object and the cause. Where theory decides the outcome (docs/model.md §4) the test
asserts it: Verlet and symplectic Euler run at 0.9x the explicit limit 2/omega_max and fail at
1.1x, RK4 (limit 2 sqrt(2)/omega_max) and implicit Euler run at both, explicit Euler and
Mesit's update fail; the sound schemes run through every other case, and implicit Euler runs
the stiff case at 10x the explicit limit.

The energy is computed here independently of the library (numpy, float64): springs, gas
-nRT ln V (continued linearly below the volume clamp, as the force), gravity, and a kinetic
energy from central differences of the per-step positions.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush.model import forces as model
from jaxplush.stepping import stability
from jaxplush.types import GAS_CONSTANT, VOLUME_EPS
from conftest import icosphere_scene

ALL = jaxplush.INTEGRATORS
SOUND = ("symplectic_euler", "rk4", "verlet", "implicit_euler")


# --------------------------------------------------------------------------- helpers

def _energy(scene, positions, dt):
    """(total, potential): (T-2,) energies per interior frame of per-step positions (T, V, 3),
    float64 numpy."""
    x = np.asarray(positions, np.float64)
    topo = model.build_topology(scene)
    p = scene.params
    m = (p.total_weight / topo.count)[topo.vertex_object]
    d = x[:, topo.edges[:, 0]] - x[:, topo.edges[:, 1]]
    l = np.linalg.norm(d, axis=-1)
    e = np.sum(0.5 * p.k_structural[topo.edge_object] * (l - topo.rest_length) ** 2, axis=1)
    e = e - np.sum(m * (x @ scene.gravity), axis=1)
    if scene.has_gas:
        vol = np.stack([scene.volumes(xi) for xi in x])
        nrt = p.nmol * GAS_CONSTANT * scene.temperature
        vc = VOLUME_EPS * topo.rest_volume
        gas = np.where(vol >= vc, -nrt * np.log(np.maximum(vol, vc)), -nrt * (np.log(vc) + (vol - vc) / vc))
        e = e + gas.sum(axis=1)
    v = (x[2:] - x[:-2]) / (2 * dt)
    return e[1:-1] + 0.5 * np.sum(m * np.sum(v * v, axis=-1), axis=1), e[1:-1]


def _run(scene, integrator, dt, steps, x0=None, v0=None, sim=None):
    """('stable', traj) or ('stopped', SimulationError); fails the test on anything else."""
    try:
        traj = jaxplush.simulate(scene, steps, dt, save_every=1, integrator=integrator, x0=x0, v0=v0,
                                 check_dt=False, sim=sim)
    except jaxplush.SimulationError as err:
        assert 0 < err.step <= steps and err.object == 0 and err.object_name == "ball"
        assert "non-finite" in err.reason or "inside out" in err.reason
        assert f"step {err.step}" in str(err) and "'ball'" in str(err)
        return "stopped", err
    assert np.isfinite(traj.positions).all()
    assert (traj.volumes > 0).all(), "the volume changed sign without a SimulationError"
    e, pe = _energy(scene, traj.positions, dt)
    # Bounded: the energy never rises above its start by more than twice the free energy in
    # play, e[0] - min(potential) (at most e[0] - E_equilibrium), and ends no higher than one
    # free energy above it. A blow-up exceeds this by orders of magnitude; what it tolerates is
    # the transient energy a floor projection injects at large steps (implicit Euler at 10x the
    # limit: +1.7 x the impact energy, decaying afterwards) and the O(h²) energy error of
    # symplectic schemes near their limit.
    free = e[0] - pe.min()
    assert e[-1] <= e[0] + free + 1e-12 * abs(e[0]) and e.max() <= e[0] + 2 * free + 1e-12 * abs(e[0]), \
        f"{integrator}: energy grew from {e[0]:.6g} to {e.max():.6g} J (free {free:.3g} J) without a SimulationError"
    return "stable", traj


_LIMITS = {}


def _limit(key, scene, x=None):
    """Verlet's explicit limit 2/omega_max (damped form) of a scene at rest, or the smaller of
    that and the limit linearised at positions x (cached under ``key``)."""
    if key not in _LIMITS:
        sim = jaxplush.make_simulator(scene, 1e-4)
        p = sim.params()
        hc = stability.estimate(sim, p).dt_max
        if x is not None:
            hc = min(hc, stability.estimate(sim, p, x).dt_max)
        _LIMITS[key] = hc
    return _LIMITS[key]


# --------------------------------------------------------------------------- scenes

@functools.lru_cache(maxsize=None)
def _inflated_ball():
    scene = icosphere_scene(subdivisions=2, k=100.0, mass=1.0, nmol=5e-4, gravity=(0, 0, 0))
    sim = jaxplush.make_simulator(scene, 1e-3)
    est = stability.estimate(sim, sim.params())
    x_eq = np.asarray(stability.inflated(sim, sim.params(), scene.vertices), np.float64)
    return scene, est.dt_max, x_eq


@functools.lru_cache(maxsize=None)
def _floor_ball():
    """A 162-vertex plush with gas and a light dashpot, its centre 0.1 m above the floor."""
    scene = icosphere_scene(subdivisions=2, radius=0.1, k=300.0, mass=0.05, nmol=1e-3, dashpot=0.005,
                            floor=0.0, translate=(0, 0.1, 0))
    return scene, _limit("floor_ball", scene)


def _squashed(scene):
    """Flattened onto the floor to 1% of its height (V = 0.01 V0): the pressure clamp is active
    for the first steps (at 4% the ball is back above 5% V0 within one step)."""
    x = scene.vertices.copy()
    x[:, 1] = 0.01 * (x[:, 1] - 0.1) + 0.001 + 0.0001
    assert scene.volumes(x)[0] < VOLUME_EPS * scene.volumes()[0]
    return x


def _dimpled(scene):
    """The cap above y = 0.15 mirrored through that plane into the ball: its faces inverted."""
    x = scene.vertices.copy()
    cap = x[:, 1] > 0.15
    x[cap, 1] = 0.3 - x[cap, 1]
    return x


def _irregular_scene():
    """An icosphere with edges split 1% from one end: 100:1 edge-length ratios, sliver faces."""
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    v, f = [list(map(tuple, m.vertices)), [list(t) for t in m.faces]]
    used = set()
    for a, b in m.edges_unique:
        if a in used or b in used:
            continue
        used.update((a, b))
        p = len(v)
        v.append(tuple(np.asarray(v[a]) + 0.01 * (np.asarray(v[b]) - np.asarray(v[a]))))
        new = []
        for t in f:
            for i in range(3):
                if {t[i], t[(i + 1) % 3]} == {a, b}:
                    u, w, c = t[i], t[(i + 1) % 3], t[(i + 2) % 3]
                    new += [[u, p, c], [p, w, c]]
                    break
            else:
                new.append(t)
        f = new
    lines = ["gravity 0 -9.81 0", "floor 0", "o ball", "k_structural 200", "total_weight 0.05", "nmol 1e-3",
             "dashpot 0.002", "translate 0 0.12 0"]
    lines += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in v]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    scene = jaxplush.parse_scene("\n".join(lines) + "\n", "<irregular>")
    topo = model.build_topology(scene)
    x = scene.vertices[scene.faces]
    area2 = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    longest = np.linalg.norm(x[:, [1, 2, 0]] - x, axis=-1).max(axis=1)
    assert topo.rest_length.max() / topo.rest_length.min() > 100
    assert (area2 / longest ** 2).min() < 1e-2          # sliver faces (smallest angle < 1 degree)
    return scene


# --------------------------------------------------------------------------- the suite

@pytest.mark.parametrize("name", ALL)
def test_explicit_limit_0_9_and_1_1(x64, name):
    """dt at 0.9x and 1.1x the explicit (Verlet) limit on the inflated ball, perturbed by 1e-4."""
    scene, hc, x_eq = _inflated_ball()
    x0 = x_eq + 1e-4 * np.random.default_rng(0).standard_normal(x_eq.shape)
    outcome = {f: _run(scene, name, f * hc, 600, x0=x0)[0] for f in (0.9, 1.1)}
    expect = {"verlet": ("stable", "stopped"), "symplectic_euler": ("stable", "stopped"),
              "rk4": ("stable", "stable"), "implicit_euler": ("stable", "stable"),
              "euler": ("stopped", "stopped"), "mesit": ("stopped", "stopped")}[name]
    assert (outcome[0.9], outcome[1.1]) == expect


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.heavy) if n in ("implicit_euler", "mesit") else n
                                  for n in ALL])
def test_stiff_springs_642_vertices(name):
    """k = 1e5 N/m on a 642-vertex plush dropped onto the floor, at 0.9x its explicit limit
    (implicit Euler also at 10x)."""
    scene = icosphere_scene(subdivisions=3, radius=0.1, k=1e5, mass=0.1, nmol=2e-3, floor=0.0,
                            translate=(0, 0.102, 0))
    hc = _limit("stiff", scene)
    v0 = np.tile([0.0, -1.0, 0.0], (scene.n_vertices, 1))
    outcome, _ = _run(scene, name, 0.9 * hc, 150, v0=v0)
    if name in SOUND:
        assert outcome == "stable"
    if name == "implicit_euler":
        outcome, traj = _run(scene, name, 10 * hc, 150, v0=v0)
        assert outcome == "stable"
        assert traj.positions[:, :, 1].min() == 0.0          # it hit the floor at 10x the limit


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.heavy) if n == "euler" else n for n in ALL])
def test_squashed_impact_and_inverted_faces(name):
    """One plush, three starts: squashed to 1% of its rest volume (the clamp activates and the
    volume never changes sign), thrown at the floor at 10 m/s, and with a cap of faces turned
    inside out (the gas pops it back). dt = 0.5x the explicit limit at rest and squashed."""
    scene, hc_rest = _floor_ball()
    squashed = _squashed(scene)
    dt = 0.5 * min(hc_rest, _limit("floor_ball_squashed", scene, squashed))
    sim = jaxplush.make_simulator(scene, dt, name)
    outcomes = {}
    with pytest.warns(UserWarning, match="pressure clamp active") if name in SOUND else _maybe_warns():
        outcomes["squash"], res = _run(scene, name, dt, 400, x0=squashed, sim=sim)
    if outcomes["squash"] == "stable":
        assert res.volumes[-1, 0] > 5 * res.volumes[0, 0]        # it re-inflated
    impact = scene.vertices.copy()
    impact[:, 1] += 0.002
    outcomes["impact"], res = _run(scene, name, dt, 400, x0=impact,
                                   v0=np.tile([0.0, -10.0, 0.0], (scene.n_vertices, 1)), sim=sim)
    if outcomes["impact"] == "stable":
        assert res.positions[:, :, 1].min() >= 0.0
    dimpled = _dimpled(scene)
    outcomes["inverted"], res = _run(scene, name, dt, 400, x0=dimpled, sim=sim)
    if outcomes["inverted"] == "stable":
        assert res.volumes[-1, 0] > res.volumes[0, 0] * 1.05     # the dimple popped out
    if name in SOUND:
        assert set(outcomes.values()) == {"stable"}, outcomes


@pytest.mark.parametrize("name", ALL)
def test_irregular_mesh_with_slivers(name):
    """100:1 edge-length ratios and sliver faces, dropped onto the floor at 0.5x its limit."""
    scene = _irregular_scene()
    dt = 0.5 * _limit("irregular", scene)
    outcome, _ = _run(scene, name, dt, 400, v0=np.tile([0.3, -2.0, 0.0], (scene.n_vertices, 1)))
    if name in SOUND:
        assert outcome == "stable"


class _maybe_warns:
    """Context that tolerates (records) warnings: unstable schemes may stop before the clamp warns."""

    def __enter__(self):
        import warnings
        self._cm = warnings.catch_warnings(record=True)
        self._cm.__enter__()
        warnings.simplefilter("always")
        return self

    def __exit__(self, *exc):
        return self._cm.__exit__(*exc)
