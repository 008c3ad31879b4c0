"""Soft-soft contact, floor friction and restitution (issue 5; docs/model.md §6, §7, §8.2).

Penetration is judged by an inside test written here independently of jaxplush.model.contact: the
generalised winding number of the other object's closed surface (solid angles, Van
Oosterom-Strackee), and the depth of an inside vertex by brute-force point-triangle distance.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush.model import contact
from jaxplush.stepping import diagnostics
from jaxplush.model import forces as model
from conftest import assert_gradient_matches_fd, icosphere_scene, icosphere_text

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# --------------------------------------------------------------------------- independent geometry


def winding_number(points, verts, faces):
    """(P,) generalised winding number of a closed triangle mesh at points (P, 3)."""
    a = verts[faces[:, 0]][None] - points[:, None]
    b = verts[faces[:, 1]][None] - points[:, None]
    c = verts[faces[:, 2]][None] - points[:, None]
    la, lb, lc = (np.linalg.norm(u, axis=-1) for u in (a, b, c))
    num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la \
        + np.einsum("pfi,pfi->pf", c, a) * lb
    return np.sum(2 * np.arctan2(num, den), axis=1) / (4 * np.pi)


def point_triangle_distance(p, verts, faces):
    """(P,) distance from points p (P, 3) to a triangle mesh, brute force (via trimesh's closest points)."""
    tri = verts[faces]
    best = np.full(len(p), np.inf)
    for i in range(0, len(faces), 256):
        t = tri[i:i + 256]
        q = trimesh.triangles.closest_point(np.repeat(t, len(p), axis=0), np.tile(p, (len(t), 1)))
        d = np.linalg.norm(q - np.tile(p, (len(t), 1)), axis=1).reshape(len(t), len(p))
        best = np.minimum(best, d.min(axis=0))
    return best


def max_penetration(scene, x):
    """Largest depth (m) of any vertex of one object inside another (0 if none)."""
    depth = 0.0
    for i, oa in enumerate(scene.objects):
        for j, ob in enumerate(scene.objects):
            if i == j:
                continue
            p = x[oa.vertex_slice[0]:oa.vertex_slice[1]]
            f = scene.faces[ob.face_slice[0]:ob.face_slice[1]]
            inside = winding_number(p, x, f) > 0.5
            if inside.any():
                depth = max(depth, float(point_triangle_distance(p[inside], x, f).max()))
    return depth


def two_balls(sub=2, gap=0.01, radius=0.1, k=200.0, mass=0.05, nmol=1e-3, gravity=(0.0, 0.0, 0.0), floor=None,
              b_offset=(0.0, 0.0, 0.0), extra_scene="", dashpot=None, drag=None):
    n = len(trimesh.creation.icosphere(subdivisions=sub).vertices)
    t = icosphere_text(subdivisions=sub, radius=radius, k=k, mass=mass, nmol=nmol, gravity=gravity, floor=floor,
                       translate=(-radius - gap / 2, 0, 0), name="a", dashpot=dashpot, drag=drag)
    t += icosphere_text(subdivisions=sub, radius=radius, k=k, mass=mass, nmol=nmol, name="b", offset=n, header=False,
                        translate=tuple(np.add((radius + gap / 2, 0, 0), b_offset)), dashpot=dashpot, drag=drag)
    return jaxplush.parse_scene(extra_scene + t, "<two balls>"), n


# --------------------------------------------------------------------------- compiled terms


def _hlo(scene):
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    # the public step is jitted itself: inside this jit its scopes read "floor/...", not "/floor/...";
    # every scope is written "/name/" here
    text = jax.jit(sim.step_fn).lower(p, sim.init_fn(p)).as_text(debug_info=True)
    return text.replace('loc("', 'loc("/'), sim


def test_single_object_scene_traces_no_contact_code():
    text, sim = _hlo(icosphere_scene(subdivisions=0, floor=-1.0))
    assert sim.terms.contact is None and sim.terms.floor_friction == 0 and sim.terms.floor_restitution == 0
    for scope in ("/contact/", "/floor_friction/", "/floor_restitution/"):
        assert scope not in text
    assert "/floor/" in text


@pytest.mark.parametrize("extra, scope", [("floor_friction 0.5\n", "/floor_friction/"),
                                          ("floor_restitution 0.5\n", "/floor_restitution/")])
def test_floor_keywords_compile_their_term(extra, scope):
    text, sim = _hlo(jaxplush.parse_scene(extra + icosphere_text(subdivisions=0, floor=-1.0), "<t>"))
    assert scope in text and "/contact/" not in text


def test_two_objects_compile_contact_unless_switched_off():
    scene, _ = two_balls(sub=0)
    text, sim = _hlo(scene)
    assert "contact" in sim.terms.names() and "/contact/" in text
    scene_off, _ = two_balls(sub=0, extra_scene="contact off\n")
    text, sim = _hlo(scene_off)
    assert sim.terms.contact is None and "/contact/" not in text


# --------------------------------------------------------------------------- scene keywords


def test_scene_keywords_are_parsed():
    scene, _ = two_balls(sub=0, floor=-1.0, extra_scene=(
        "floor_friction 0.4\nfloor_restitution 0.3\ncontact_stiffness 50\ncontact_thickness 0.002\n"
        "contact_capacity 7\nself_collision on\n"))
    assert (scene.floor_friction, scene.floor_restitution) == (0.4, 0.3)
    assert (scene.contact_stiffness, scene.contact_thickness, scene.contact_capacity) == (50.0, 0.002, 7)
    cfg = model.Terms.for_scene(scene).contact
    assert cfg.stiffness == 50.0 and cfg.thickness == (0.002,) and cfg.capacity == (7, 7)
    assert cfg.self_objects == (0, 1) and cfg.self_thickness == (0.002, 0.002)
    default = model.Terms.for_scene(two_balls(sub=0)[0]).contact
    assert default.stiffness is None and default.self_objects == ()


def test_headroom_near_a_whole_object_takes_the_whole_object():
    """The fit's headroom doubles each object's candidate capacity, at most to its vertex count;
    a doubled capacity within an eighth of the count becomes the count (the same cost, and it
    cannot overflow: 640 of 642 overflowed mid-fit and its growth to 642 recompiled everything)."""
    scene, _ = two_balls(sub=0, extra_scene="contact_capacity 3\n")              # 12 vertices each
    terms = model.Terms.for_scene(scene)
    sizes = contact.object_sizes(scene)
    assert sizes == (12, 12)
    assert contact.with_headroom(terms, sizes).contact.capacity == (6, 6)         # half: kept
    near = contact.with_capacity(terms, 11)                                       # 22 -> 12
    assert contact.with_headroom(near, sizes).contact.capacity == (12, 12)
    five = contact.with_capacity(terms, 5)                                        # 10 of 12 (0.83): kept
    assert contact.with_headroom(five, sizes).contact.capacity == (10, 10)
    assert contact.with_headroom(five, sizes, factor=1, least=11).contact.capacity == (12, 12)  # 11 of 12


@pytest.mark.parametrize("line, message", [
    ("floor_friction -1", "'floor_friction' -1 must be >= 0"),
    ("floor_restitution 1.5", "must be between 0 and 1"),
    ("contact_stiffness 0", "must be > 0"),
    ("contact_thickness x", "expects a number"),
    ("contact_capacity 2.5", "must be an integer >= 1"),
    ("contact_friction -0.5", "'contact_friction' -0.5 must be >= 0"),
    ("contact_friction nan", "contact_friction"),
    ("contact maybe", "'contact' expects 'on' or 'off'"),
    ("self_collision", "'self_collision' expects 'on' or 'off'"),
])
def test_bad_contact_keywords_name_file_and_line(line, message):
    text = "floor -1\n" + line + "\n" + icosphere_text(subdivisions=0, header=False)
    with pytest.raises(jaxplush.SceneError) as e:
        jaxplush.parse_scene(text, "pile.obj")
    assert e.value.line == 2 and message in str(e.value) and str(e.value).startswith("pile.obj:2:")


def test_floor_friction_without_floor_is_an_error():
    with pytest.raises(jaxplush.SceneError, match="'floor_friction' needs a 'floor'"):
        jaxplush.parse_scene("floor_friction 0.5\n" + icosphere_text(subdivisions=0), "s.obj")


# --------------------------------------------------------------------------- the force


def _contact_force(sim, p, x):
    """Contact part of the internal force (V, 3): the full force minus the same without contact."""
    bare = jaxplush.make_simulator(sim.scene, sim.dt, terms=dataclasses.replace(sim.terms, contact=None))
    v = jnp.zeros_like(x)
    return np.asarray(sim.force_fn(p, x, v)[0] - bare.force_fn(p, x, v)[0])


def test_contact_force_conserves_momentum_and_matches_both_assemblies(x64):
    scene, n = two_balls(sub=1, gap=-0.01)            # overlapping by 1 cm
    sim = jaxplush.make_simulator(scene, 1e-4)
    seg = jaxplush.make_simulator(scene, 1e-4, assembly="segment")
    p = sim.params()
    rng = np.random.default_rng(0)
    x = jnp.asarray(scene.vertices + 1e-3 * rng.standard_normal(scene.vertices.shape))
    f = _contact_force(sim, p, x)
    scale = np.abs(f).max()
    assert scale > 1.0                                  # there is contact
    np.testing.assert_allclose(f.sum(0), 0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.cross(np.asarray(x), f).sum(0), 0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(_contact_force(seg, p, x), f, rtol=1e-12, atol=1e-12 * scale)
    # A repels B: the force on A points to -x, on B to +x.
    assert f[:n, 0].sum() < 0 < f[n:, 0].sum()
    # It is -dU/dx of the contact energy.
    energy = contact.make_contact_energy(sim.topology, sim.terms.contact)
    g = jax.jit(jax.grad(lambda y: energy(p, y.T)[0]))(x)
    np.testing.assert_allclose(-np.asarray(g), f, atol=1e-10 * scale)


def test_deeply_penetrating_vertices_are_pushed_out(x64):
    """The pseudo-normal inside test: vertices of A well inside B feel a force out of B."""
    scene, n = two_balls(sub=2, gap=-0.06,            # 6 cm overlap, deeper than the thickness (1.5 cm)
                         extra_scene="contact_capacity 162\n")   # every vertex may be a candidate
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    x = np.asarray(scene.vertices)
    f = _contact_force(sim, p, jnp.asarray(x))
    fb = scene.faces[scene.objects[1].face_slice[0]:scene.objects[1].face_slice[1]]
    inside = winding_number(x[:n], x, fb) > 0.5
    assert inside.sum() > 5
    centre_b = x[n:].mean(0)
    outward = x[:n][inside] - centre_b
    assert np.all(np.einsum("ij,ij->i", f[:n][inside], outward) > 0)


# --------------------------------------------------------------------------- dynamics


def _energy_series(sim, p, state, chunks, steps):
    e_contact = jax.jit(contact.make_contact_energy(sim.topology, sim.terms.contact))
    out, states = [], []
    for _ in range(chunks + 1):
        e = diagnostics.energies(sim, p, state)["total"] + float(e_contact(p, state.x.T)[0])
        out.append(e)
        states.append(state)
        state, _, health = jaxplush.rollout(sim, p, state, 1, steps)
        assert not health.failed
    return np.array(out), states


@pytest.mark.heavy
def test_zero_gravity_collision_conserves_momentum_and_energy(x64):
    scene, n = two_balls(sub=2, gap=0.02)
    sim = jaxplush.make_simulator(scene, 2e-4)
    p = sim.params()
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 1.0, -1.0                  # thrown at each other at 2 m/s closing speed
    v0[n:, 1] = 0.2                                   # slightly off-centre: a glancing blow
    state = sim.init_fn(p, None, v0)
    energies, states = _energy_series(sim, p, state, chunks=30, steps=25)
    m = np.asarray(model.vertex_mass(sim.topology, p))[:, None]
    mom = np.array([(m * np.asarray(s.v)).sum(0) for s in states])
    np.testing.assert_allclose(mom, np.broadcast_to(mom[0], mom.shape), atol=1e-10 * np.abs(mom[0]).sum())
    xs = np.array([np.asarray(s.x) for s in states])
    # They collided and came apart again: A moves back to -x.
    va = np.array([(np.asarray(s.v)[:n, 0]).mean() for s in states])
    assert va[0] > 0.9 and va[-1] < -0.3
    kin0 = 0.5 * float(np.sum(m * v0 ** 2))
    assert np.max(energies - energies[0]) < 0.01 * kin0
    assert max(max_penetration(scene, x) for x in xs) < 1e-3


def test_dropped_onto_each_other_and_the_floor_comes_to_rest():
    """Ball b falls onto ball a (off-centre), which sits on the floor; both end at rest, no overlap."""
    scene, n = two_balls(sub=2, gap=0.0, k=300.0, floor=-0.101, gravity=(0.0, -9.81, 0.0), dashpot=0.02, drag=5.0,
                         b_offset=(-0.15, 0.25, 0.0), extra_scene="floor_friction 0.5\n")
    dt, every = 2.5e-4, 250
    traj = jaxplush.simulate(scene, steps=5000, dt=dt, save_every=every, check_dt=False)
    assert np.isfinite(traj.positions).all()
    assert max(max_penetration(scene, x) for x in traj.positions) < 1e-3
    com = np.stack([traj.positions[:, :n].mean(1), traj.positions[:, n:].mean(1)], axis=1)
    assert np.abs(com[-1] - com[-5]).max() / (4 * every * dt) < 0.03   # at rest (it hit at about 2 m/s)
    assert com[:, 1, 1].max() > com[:, 0, 1].max() + 0.15              # b was above a and landed on it
    assert traj.positions[-1, :, 1].min() > scene.floor - 1e-6


def _box_mesh(extents=(0.2, 0.08, 0.2)):
    return trimesh.creation.box(extents=extents).subdivide().subdivide()


def box_text(mu=0.5, tilt_deg=0.0, extents=(0.2, 0.08, 0.2), name="box", translate_y=None, offset=0,
             header=True, shift_x=0.0, nmol=0.002, dashpot=0.02):
    """A gas-filled cushion (a subdivided box) resting on the floor at y = 0 (or at translate_y)."""
    m = _box_mesh(extents)
    g = [float(c) for c in 9.81 * np.array([np.sin(np.radians(tilt_deg)), -np.cos(np.radians(tilt_deg)), 0.0])]
    out = [f"gravity {g[0]!r} {g[1]!r} {g[2]!r}", "floor 0", f"floor_friction {mu!r}"] if header else []
    ty = extents[1] / 2 if translate_y is None else translate_y
    out += [f"o {name}", "k_structural 400", "total_weight 0.1", f"nmol {nmol!r}", f"dashpot {dashpot!r}",
            f"translate {shift_x!r} {ty!r} 0"]
    out += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
    out += [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in m.faces]
    out.append("END_OBJECT")
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("tilt, sticks", [(15.0, True), (40.0, False)])
def test_friction_sticks_below_and_slides_above_the_friction_angle(tilt, sticks):
    mu, dt = 0.5, 2e-4                                 # friction angle atan(0.5) = 26.6 deg
    # settle the cushion under vertical gravity (with air drag), then tilt gravity from rest
    settle = jaxplush.parse_scene(box_text(mu=mu, nmol=5e-5, dashpot=0.05).replace("dashpot 0.05", "dashpot 0.05\ndrag 30"),
                                  "<settle>")
    x0 = jaxplush.simulate(settle, steps=2000, dt=dt, save_every=2000, check_dt=False).positions[-1]
    scene = jaxplush.parse_scene(box_text(mu=mu, tilt_deg=tilt, nmol=5e-5, dashpot=0.05), "<box>")
    steps = 1500
    traj = jaxplush.simulate(scene, steps=steps, dt=dt, save_every=steps, x0=x0, check_dt=False)
    shift = traj.positions[-1, :, 0].mean() - traj.positions[0, :, 0].mean()
    t = steps * dt
    th = np.radians(tilt)
    if sticks:
        assert abs(shift) < 1e-3                        # frictionless it would slide 0.5 g sin t² = 11 cm
    else:
        expected = 0.5 * 9.81 * (np.sin(th) - mu * np.cos(th)) * t ** 2
        assert 0.7 * expected < shift < 1.3 * expected


def _stacked_cushions(mu, tilt, drag=None):
    """A small cushion on a large one on a sticky floor, with soft-soft friction mu."""
    lower = box_text(mu=2.0, tilt_deg=tilt, extents=(0.36, 0.05, 0.36), name="lower", nmol=1e-4, dashpot=0.05)
    n = len(_box_mesh((0.36, 0.05, 0.36)).vertices)
    upper = box_text(tilt_deg=tilt, extents=(0.16, 0.05, 0.16), name="upper", translate_y=0.11, offset=n,
                     header=False, nmol=2e-5, dashpot=0.05)
    text = f"contact_friction {mu!r}\ncontact_capacity {n}\n" + lower + upper   # every vertex may be near
    if drag:
        text = text.replace("dashpot 0.05", f"dashpot 0.05\ndrag {drag!r}")
    return jaxplush.parse_scene(text, "<cushions>"), n


@functools.lru_cache(maxsize=None)
def _settled_cushions(mu, dt):
    """The stack settled under vertical gravity (with air drag), shared by both tilts."""
    settle, n = _stacked_cushions(mu, 0.0, drag=30.0)
    return jaxplush.simulate(settle, steps=2000, dt=dt, save_every=2000, check_dt=False).positions[-1], n


@pytest.mark.heavy
@pytest.mark.parametrize("tilt, sticks", [(15.0, True), (40.0, False)])
def test_contact_friction_resists_below_and_slides_above_the_friction_angle(tilt, sticks):
    """Soft-soft friction is explicit and velocity level: below the friction angle it does not
    hold exactly (the jiggling cushions creep), but it removes most of the sliding; above it the
    cushion slides as Coulomb's kinetic law says."""
    mu, dt = 0.5, 1.25e-4                              # friction angle atan(0.5) = 26.6 deg
    x0, n = _settled_cushions(mu, dt)
    scene, _ = _stacked_cushions(mu, tilt)
    assert "contact_friction" in jaxplush.make_simulator(scene, dt).terms.names()
    steps = 2000
    traj = jaxplush.simulate(scene, steps=steps, dt=dt, save_every=steps, x0=x0, check_dt=False)
    x = traj.positions[:, :, 0]
    slide = (x[-1, n:].mean() - x[0, n:].mean()) - (x[-1, :n].mean() - x[0, :n].mean())
    t = steps * dt
    th = np.radians(tilt)
    frictionless = 0.5 * 9.81 * np.sin(th) * t ** 2
    if sticks:
        assert abs(slide) < 0.3 * frictionless          # 18 mm against 79 mm without friction
    else:
        expected = 0.5 * 9.81 * (np.sin(th) - mu * np.cos(th)) * t ** 2
        assert 0.7 * expected < slide < 1.3 * expected, (slide, expected)


@pytest.mark.parametrize("restitution", [0.0, 0.8])
def test_floor_restitution_reflects_each_impacting_vertex(restitution):
    """``floor_restitution E`` acts per vertex (jaxplush.stepping.constraints): a vertex that reaches the floor
    much faster than v_rest = 2 |g| dt leaves it with E times its incoming normal speed, a slow one
    is only projected onto the floor (it lands, so resting vertices do not jitter), and a vertex
    above the floor is untouched. (A gas-filled body as a whole does not rebound measurably more with
    it, docs/contact.md "Limits": its springs and gas take the energy of the impact.)"""
    from jaxplush.stepping.constraints import make_constrain
    text = icosphere_text(subdivisions=0, radius=0.05, k=300.0, mass=0.05, floor=0.0, translate=(0, 0.2, 0))
    if restitution:
        text = f"floor_restitution {restitution!r}\n" + text
    scene = jaxplush.parse_scene(text, "<ball>")
    dt = 1e-4
    sim = jaxplush.make_simulator(scene, dt)
    constrain = make_constrain(sim.topology, sim.terms, scene, dt)
    v_rest = 2 * 9.81 * dt
    n = scene.n_vertices
    x_old = np.zeros((3, n))
    x_old[1] = 0.01
    v_in = np.zeros((3, n))
    v_in[1, 0], v_in[1, 1], v_in[1, 2] = -3.0, -0.2 * v_rest, -1.0        # fast, slow, and one that stays up
    v_in[0, 0] = 0.5                                                        # tangential speed is kept
    x_old[1, 0], x_old[1, 1] = 1e-4, 2e-8                                   # 0 and 1 start just above the floor
    x_new = x_old + v_in * dt
    x_new[1, 2] = 0.01 - 1e-4                                               # vertex 2 moved but stays above
    x, v = (np.asarray(a) for a in constrain(jnp.asarray(x_old), jnp.asarray(x_new), jnp.asarray(v_in)))
    assert np.all(x[1] >= 0.0) and x[1, 0] == 0.0 and x[1, 1] == 0.0
    land = (0.0 - x_old[1, 0]) / dt                                          # the velocity that lands it
    expect = restitution * 3.0 if restitution else land
    assert v[1, 0] == pytest.approx(expect, rel=1e-3, abs=1e-9)
    slow_land = (0.0 - x_old[1, 1]) / dt
    if restitution:          # slow: it leaves with at most a fifth of E times its speed (a smooth switch)
        assert slow_land < v[1, 1] <= 0.2 * restitution * 0.2 * v_rest
    else:
        assert v[1, 1] == pytest.approx(slow_land, rel=1e-3)
    assert v[0, 0] == pytest.approx(0.5) and v[1, 2] == pytest.approx(-1.0) and x[1, 2] == pytest.approx(x_new[1, 2])


# --------------------------------------------------------------------------- gradients


@pytest.mark.heavy
def test_gradients_through_a_collision_match_finite_differences(x64):
    """Two balls thrown at each other collide and bounce apart within the horizon; the loss on the
    final frame depends on the contact force throughout."""
    scene, n = two_balls(sub=1, gap=0.01, k=150.0)
    sim = jaxplush.make_simulator(scene, 2e-4)
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 0.6, -0.6

    def loss(k, nmol, s=sim):
        p = s.params()._replace(k_structural=k, nmol=nmol)
        _, frames, _ = jaxplush.rollout(s, p, s.init_fn(p, None, v0), 1, 150)
        x = frames[-1]
        return jnp.mean(x[:n, 0]) - jnp.mean(x[n:, 0]) + jnp.mean(x[:n, 0] ** 2)

    p0 = sim.params()
    k0, n0 = p0.k_structural, p0.nmol
    # they collide: without contact they would pass through each other
    ghost = jaxplush.make_simulator(scene, 2e-4, terms=dataclasses.replace(sim.terms, contact=None))
    assert float(loss(k0, n0, ghost)) > float(loss(k0, n0)) + 0.05

    @jax.jit
    def log_loss(theta):                       # theta = log(k_A, k_B, nmol_A, nmol_B)
        return loss(jnp.exp(theta[:2]), jnp.exp(theta[2:]))

    theta = jnp.log(jnp.concatenate([k0, n0]))
    g = np.asarray(jax.grad(log_loss)(theta))
    assert np.isfinite(g).all()
    # Whole-vector comparison, relative to the gradient's norm, once the differences have converged.
    # Steps of 1e-3 and 1e-4 in log space: at 1e-5 a vertex's closest face switches within the
    # step, the loss has a kink there and the differences scatter by a few percent (rough, not wrong).
    assert_gradient_matches_fd(log_loss, np.asarray(theta), g, h=1e-3, rtol=1e-3)


# --------------------------------------------------------------------------- capacity, self-collision


@pytest.mark.heavy
def test_capacity_overflow_is_detected_and_simulate_reruns_with_a_larger_capacity():
    scene, n = two_balls(sub=1, gap=-0.005, extra_scene="contact_capacity 4\n")
    sim = jaxplush.make_simulator(scene, 1e-4)
    # the compiled rollout cannot be exact: its health says so from the first saved frame on (a
    # status, not a NaN), and the report says why
    p = sim.params()
    _, frames, health = jaxplush.rollout(sim, p, sim.init_fn(p), 2, 10)
    assert health.failed and np.isfinite(np.asarray(frames)).all()
    assert (np.asarray(health.code) == diagnostics.CONTACT_OVERFLOW).all() and (np.asarray(health.bad_step) == 10).all()
    report = contact.capacity_report(sim, scene.vertices)
    assert report is not None and "contact_capacity" in report
    need = contact.needed_capacity(sim, scene.vertices)
    assert need > 4
    bigger = jaxplush.make_simulator(scene, 1e-4, terms=contact.with_capacity(sim.terms, need))
    assert contact.capacity_report(bigger, scene.vertices) is None
    ref = jaxplush.simulate(scene, steps=20, dt=1e-4, save_every=10, check_dt=False, sim=bigger)
    assert np.isfinite(ref.positions).all()
    # simulate() handles it outside jit: it reruns with a larger capacity and says so
    with pytest.warns(UserWarning, match=r"at step 1 \(\d+ needed, capacity 4\); reran with contact_capacity"):
        traj = jaxplush.simulate(scene, steps=20, dt=1e-4, save_every=10, check_dt=False)
    assert any("contact_capacity" in w for w in traj.warnings)
    np.testing.assert_allclose(traj.positions, ref.positions, rtol=0, atol=1e-5)   # capacity does not change it


@pytest.mark.heavy
def test_capacity_overflow_that_cannot_be_fixed_is_a_clear_error(monkeypatch):
    import importlib
    monkeypatch.setattr(importlib.import_module("jaxplush.stepping.simulation"), "MAX_CAPACITY_RETRIES", 0)
    scene, n = two_balls(sub=1, gap=-0.005, extra_scene="contact_capacity 4\n")
    with pytest.raises(jaxplush.SimulationError) as e:
        jaxplush.simulate(scene, steps=20, dt=1e-4, save_every=10, check_dt=False)
    assert e.value.step == 1
    assert "contact_capacity" in str(e.value)          # the error says what to raise, not just "NaN"
    assert diagnostics.MESSAGES[diagnostics.CONTACT_OVERFLOW] in str(e.value)


def _overflowing(coherent=True):
    """Two overlapping 42-vertex balls whose candidates overflow object a's capacity (4) only: b's
    capacity holds all its vertices."""
    scene, n = two_balls(sub=1, gap=-0.005)
    base = jaxplush.make_simulator(scene, 1e-4)
    terms = dataclasses.replace(base.terms, contact=dataclasses.replace(base.terms.contact, capacity=(4, n)))
    sim = jaxplush.make_simulator(scene, 1e-4, terms=terms, coherent_contact=coherent)
    ((_, n_a, n_b, cap_a, cap_b),) = contact.candidate_counts(sim, scene.vertices)
    assert n_a > cap_a == 4 and n_b <= cap_b == n
    return scene, n, sim


@pytest.mark.heavy
@pytest.mark.parametrize("coherent", [True, False], ids=["carried-lists", "search-every-step"])
def test_an_overflowing_rollout_reports_the_object_and_stays_finite(coherent):
    scene, n, sim = _overflowing(coherent)
    p = sim.params()
    final, frames, health = jaxplush.rollout(sim, p, sim.init_fn(p), 3, 5)
    assert np.isfinite(np.asarray(frames)).all() and np.isfinite(np.asarray(final.x)).all()
    assert health.failed
    np.testing.assert_array_equal(np.asarray(health.code), [diagnostics.CONTACT_OVERFLOW, diagnostics.OK])
    np.testing.assert_array_equal(np.asarray(health.bad_step), [5, -1])        # the first saved frame
    assert int(health.good_step) == 0
    # the force uses the candidates that fit: finite (inexact), still equal and opposite
    f, _ = sim.force_fn(p, scene.vertices, np.zeros_like(scene.vertices))
    f = np.asarray(f, np.float64)
    assert np.isfinite(f).all()
    assert np.linalg.norm(f.sum(axis=0)) <= 1e-5 * np.linalg.norm(f[:n].sum(axis=0))
    # the located failure is the first step, with the overflow's code
    assert jaxplush.stepping.rollouts.locate_failure(sim, p, health) == (1, 0, diagnostics.CONTACT_OVERFLOW)


def test_status_fn_reports_a_state_whose_candidates_overflow():
    scene, n, sim = _overflowing()
    p = sim.params()
    state = sim.init_fn(p)
    status = jax.jit(sim.status_fn)
    np.testing.assert_array_equal(np.asarray(status(p, state)), [diagnostics.CONTACT_OVERFLOW, diagnostics.OK])
    apart = state._replace(x=state.x.at[n:, 0].add(0.5))                     # b 0.5 m away: no candidates
    assert contact.needed_capacity(sim, np.asarray(apart.x)) == 0
    np.testing.assert_array_equal(np.asarray(status(p, apart)), [diagnostics.OK, diagnostics.OK])
    # with the default capacity the same state is fine
    ok = jaxplush.make_simulator(scene, 1e-4)
    np.testing.assert_array_equal(np.asarray(ok.status_fn(p, state)), [diagnostics.OK, diagnostics.OK])


@pytest.mark.heavy
def test_gradients_through_an_overflowing_rollout_are_finite():
    """No NaN leaks from an overflow into values or gradients of a rollout; fitting's rollout loss
    is NaN (the fit's signal to raise the capacity), its gradient finite."""
    from jaxplush.fitting.objective.gradients import rollout_loss
    scene, n, sim = _overflowing()
    p = sim.params()

    def loss(k):
        q = p._replace(k_structural=k)
        _, frames, _ = jaxplush.rollout(sim, q, sim.init_fn(q), 2, 5)
        return jnp.sum((frames[-1] - scene.vertices) ** 2)

    val, g = jax.value_and_grad(loss)(p.k_structural)
    assert np.isfinite(float(val)) and np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).max() > 0
    target = jnp.asarray(np.stack([scene.vertices] * 2), jnp.float32)

    def fit_loss(k, method, nan_on_overflow=True):
        q = p._replace(k_structural=k)
        return rollout_loss(sim, q, sim.init_fn(q), (5, 10), lambda x, a: jnp.sum((x - a) ** 2), target,
                            method=method, nan_on_overflow=nan_on_overflow)

    # only the value says it: the gradient is that of the (inexact) run, for every method
    v2, g2 = jax.value_and_grad(fit_loss)(p.k_structural, "plain", False)
    assert np.isfinite(float(v2)) and float(v2) > 0
    for method in ("plain", "adjoint"):
        v, g = jax.value_and_grad(fit_loss)(p.k_structural, method)
        assert np.isnan(float(v)) and np.isfinite(np.asarray(g)).all(), method
        assert np.linalg.norm(np.asarray(g - g2)) <= 1e-4 * np.linalg.norm(np.asarray(g2)), method


def test_self_collision_repels_a_folded_surface(x64):
    scene = jaxplush.parse_scene("self_collision on\n" + icosphere_text(subdivisions=2), "<s>")
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    energy = jax.jit(contact.make_contact_energy(sim.topology, sim.terms.contact))
    x = np.asarray(scene.vertices)
    assert float(energy(p, jnp.asarray(x.T))[0]) < 1e-12      # a round ball does not touch itself
    flat = x * np.array([1.0, 0.03, 1.0])                      # squashed: top and bottom 6 mm apart
    u, overflow = energy(p, jnp.asarray(flat.T))
    assert float(u) > 0 and not bool(overflow)
    f = -np.asarray(jax.jit(jax.grad(lambda y: energy(p, y)[0]))(jnp.asarray(flat.T))).T
    top = flat[:, 1] > 0.002
    bottom = flat[:, 1] < -0.002
    assert f[top, 1].sum() > 0 > f[bottom, 1].sum()            # the two sheets are pushed apart


# --------------------------------------------------------------------------- temporal coherence


def _thrown(sub=2, gap=0.02):
    scene, n = two_balls(sub=sub, gap=gap)
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 1.0, -1.0
    v0[n:, 1] = 0.2
    return scene, n, v0


@pytest.mark.heavy
@pytest.mark.parametrize("coherent", [True, False], ids=["carried-lists", "search-every-step"])
def test_an_overflow_between_saved_frames_is_not_lost(coherent):
    """Capacity 60: the lists fit at the start (51 candidates) and at the end, but not while the
    balls collide in between (up to about 90): the one saved frame still reports the overflow, and
    simulate reruns with the capacity the states in between need, reproducing the exact run."""
    scene, n, v0 = _thrown()
    exact = jaxplush.make_simulator(scene, 2e-4)
    terms = dataclasses.replace(exact.terms, contact=dataclasses.replace(exact.terms.contact, capacity=(60, 60)))
    sim = jaxplush.make_simulator(scene, 2e-4, terms=terms, coherent_contact=coherent)
    p = sim.params()
    s0 = sim.init_fn(p, None, v0)
    final, frames, health = jaxplush.rollout(sim, p, s0, 1, 300)
    assert np.isfinite(np.asarray(frames)).all()
    assert contact.needed_capacity(sim, scene.vertices) <= 60 and contact.needed_capacity(sim, np.asarray(final.x)) <= 60
    assert int(sim.status_fn(p, final).max()) < diagnostics.ERROR              # the end state alone is fine
    np.testing.assert_array_equal(np.asarray(health.code), [diagnostics.CONTACT_OVERFLOW] * 2)
    np.testing.assert_array_equal(np.asarray(health.bad_step), [300, 300])
    if not coherent:
        from jaxplush.fitting.judge.identifiability import frames_at_steps
        fr, codes = jax.jit(lambda q: frames_at_steps(sim, q, sim.init_fn(q, None, v0), (0, 300)))(p)
        np.testing.assert_array_equal(np.asarray(codes), [[diagnostics.OK] * 2, [diagnostics.CONTACT_OVERFLOW] * 2])
        assert np.linalg.norm(np.asarray(fr[-1] - final.x)) <= 1e-4 * np.linalg.norm(np.asarray(final.x))
        return
    with pytest.warns(UserWarning, match=r"contact candidates overflowed at step \d+ \(\d+ needed, capacity 60\)"):
        traj = jaxplush.simulate(scene, 300, 2e-4, save_every=300, v0=v0, sim=sim, check_dt=False)
    ref = jaxplush.simulate(scene, 300, 2e-4, save_every=300, v0=v0, sim=exact, check_dt=False)
    assert not ref.warnings
    assert np.linalg.norm(traj.positions - ref.positions) <= 1e-4 * np.linalg.norm(ref.positions)


@pytest.mark.heavy
def test_carried_candidate_lists_give_the_search_every_step_result():
    """Rollouts carry the candidate lists (rebuilt past half the skin, nearest vertices walked):
    a glancing collision then follows the search-every-step trajectory to float32 rounding."""
    scene, n, v0 = _thrown()
    sim = jaxplush.make_simulator(scene, 2e-4)
    ref = jaxplush.make_simulator(scene, 2e-4, terms=sim.terms, coherent_contact=False)
    assert sim.internal.coherent is not None and ref.internal.coherent is None
    p = sim.params()
    out = [jaxplush.rollout(s, p, s.init_fn(p, None, v0), 30, 25) for s in (sim, ref)]
    assert not out[0][2].failed and not out[1][2].failed
    fa, fb = np.asarray(out[0][1]), np.asarray(out[1][1])
    va = np.asarray(out[0][0].v)[:n, 0].mean()
    assert va < -0.3                                  # they collided and came apart
    assert np.max(np.abs(fa - fb)) < 1e-4             # m, over 750 steps and a collision


def test_contact_cache_is_rebuilt_when_a_watched_vertex_moves_half_the_skin_or_another_comes_near():
    scene, n = two_balls(sub=2, gap=0.0)
    sim = jaxplush.make_simulator(scene, 1e-4)
    skin = contact.skin_distance(sim.topology, sim.terms.contact)
    _, ops = contact.make_contact(sim.topology, sim.terms.contact)
    x = jnp.asarray(scene.vertices).T
    cache = ops.init(x)
    assert cache.overflow.shape == (2,) and not np.asarray(cache.overflow).any() and int(cache.valid.sum()) > 0
    update = jax.jit(ops.update)
    # every vertex moved by 0.4 skin: no rebuild; each target walked to the nearest of itself and
    # its two-ring
    shift = jnp.asarray([0.0, 0.4 * skin, 0.0])[:, None]
    x1 = x.at[:, n:].add(shift)
    c1 = update(cache, x1)
    np.testing.assert_array_equal(np.asarray(c1.x_ref), np.asarray(x))
    np.testing.assert_array_equal(np.asarray(c1.q_idx), np.asarray(cache.q_idx))
    ring = np.asarray(sim.topology.ring)
    xn = np.asarray(x1).T
    for q, t, t1, ok in zip(*(np.asarray(a) for a in (cache.q_idx, cache.target, c1.target, cache.valid))):
        if ok:
            cand = np.concatenate([[t], ring[t], ring[ring[t]].ravel()])
            d = np.sum((xn[cand] - xn[q]) ** 2, axis=1)
            assert np.isclose(np.sum((xn[t1] - xn[q]) ** 2), d.min(), rtol=1e-5, atol=1e-12)
    # one vertex near the other ball (watched) moved past half the skin: rebuilt at the new
    # positions (a fresh search)
    watch = np.asarray(cache.watch)
    xa, xb = np.asarray(x)[:, :n], np.asarray(x)[:, n:]
    near = int(np.argmin(np.sum((xa - xb.mean(axis=1, keepdims=True)) ** 2, axis=0)))
    far = int(np.argmax(np.sum((xa - xb.mean(axis=1, keepdims=True)) ** 2, axis=0)))
    assert watch[near] and not watch[far] and 0 < watch.sum() < len(watch)
    x2 = x.at[1, near].add(0.6 * skin)
    c2 = update(cache, x2)
    fresh = ops.init(x2)
    np.testing.assert_array_equal(np.asarray(c2.x_ref), np.asarray(x2))
    for a, b in zip(c2, fresh):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a vertex far from the other ball moves freely (no rebuild: the lists stay), until it comes
    # near the other ball's box and sphere (rebuilt)
    x3 = x.at[1, far].add(3.0 * skin)
    assert not bool(ops.stale(cache, x3))
    np.testing.assert_array_equal(np.asarray(update(cache, x3).x_ref), np.asarray(x))
    x4 = x.at[:, far].set(xb.mean(axis=1) + np.asarray([0.0, 0.0, 1.05]) * np.ptp(xb, axis=1).max() / 2)
    assert bool(ops.stale(cache, x4))
    np.testing.assert_array_equal(np.asarray(update(cache, x4).x_ref), np.asarray(x4))
    # an overflow flag stays set, through a walk and through a rebuild that does not overflow
    flagged = cache._replace(overflow=jnp.asarray([False, True]))
    for x_new in (x1, x2):
        np.testing.assert_array_equal(np.asarray(update(flagged, x_new).overflow), [False, True])


def test_the_walk_reaches_a_nearest_vertex_two_rings_away():
    """Between rebuilds each query's nearest vertex is walked over its two-ring. A walk over the
    one-ring can stop at a vertex nearer than its neighbours while the nearest vertex lies two
    rings away (the force then reads the wrong faces until the next rebuild): here every query's
    target is set two rings from its nearest vertex, where the best of the one-ring cannot be it,
    and one walk finds a vertex as near as a fresh search's."""
    scene, n = two_balls(sub=2, gap=0.002)
    sim = jaxplush.make_simulator(scene, 1e-4)
    _, ops = contact.make_contact(sim.topology, sim.terms.contact)
    x = jnp.asarray(scene.vertices).T
    cache = ops.init(x)
    ring = np.asarray(sim.topology.ring)
    xn = np.asarray(x).T
    q_idx, target, valid = (np.asarray(a) for a in (cache.q_idx, cache.target, cache.valid))
    assert valid.sum() >= 10
    moved = target.copy()
    d2 = lambda q, v: np.sum((xn[v] - xn[q]) ** 2, axis=-1)            # noqa: E731
    for i in np.nonzero(valid)[0]:
        t = target[i]
        one = set(ring[t].tolist())
        two = sorted(set(ring[ring[t]].ravel().tolist()) - one - {t})
        a = two[int(np.argmax(d2(q_idx[i], np.asarray(two))))]          # the farthest two rings away
        moved[i] = a
        best_one = np.concatenate([[a], ring[a]])
        assert d2(q_idx[i], best_one).min() > d2(q_idx[i], t)            # the one-ring walk falls short
    walked = np.asarray(jax.jit(ops.walk)(cache._replace(target=jnp.asarray(moved)), x).target)
    for i in np.nonzero(valid)[0]:
        np.testing.assert_allclose(d2(q_idx[i], walked[i]), d2(q_idx[i], target[i]), rtol=1e-6)


def test_two_rings_hold_each_vertex_and_its_neighbours_neighbours_once():
    sim = jaxplush.make_simulator(two_balls(sub=1)[0], 1e-4)
    ring = np.asarray(sim.topology.ring)
    table = contact.two_rings(ring)
    assert table.shape[1] == contact.two_ring_width(ring) == 19        # valence <= 6: 1 + 3 x 6
    for v in range(len(ring)):
        want = {v} | set(ring[v].tolist()) | set(ring[ring[v]].ravel().tolist())
        assert table[v, 0] == v and set(table[v].tolist()) == want
        real = table[v][table[v] != v]
        assert len(real) == len(set(real.tolist())) == len(want) - 1


@pytest.mark.heavy
def test_carried_lists_hold_every_vertex_in_reach():
    """The skin argument: at every step of a collision, each vertex within the force's reach of the
    other object (2 delta of its surface, so within 2 delta + an edge of one of its vertices: the
    query filter without the skin) is among the carried queries."""
    scene, n, v0 = _thrown()
    sim = jaxplush.make_simulator(scene, 2e-4)
    p = sim.params()
    cfg = sim.terms.contact
    reach = contact._near_limits(sim.topology, cfg)[0] - contact.skin_distance(sim.topology, cfg)
    co = sim.internal.coherent

    @jax.jit
    def run(state, cache):
        def body(c, _):
            s, k = co.step(p, *c)
            return (s, k), (s.x, k.q_idx, k.valid)
        return jax.lax.scan(body, (state, cache), None, length=600)[1]

    s0 = sim.internal.to_internal(sim.init_fn(p, None, v0))
    xs, qs, valid = (np.asarray(a) for a in run(s0, co.init(s0.x)))
    rebuilds = touching = 0
    for i in range(0, 600, 3):
        x = xs[i]                                        # (3, V) after step i; the lists of step i + 1
        d = np.sqrt(np.sum((x[:, :n, None] - x[:, None, n:]) ** 2, axis=0))      # (n_a, n_b) vertex distances
        in_a, in_b = d.min(axis=1) <= reach, d.min(axis=0) <= reach
        have = set(qs[i][valid[i]].tolist())
        need = set(np.nonzero(in_a)[0].tolist()) | set((n + np.nonzero(in_b)[0]).tolist())
        assert need <= have, f"step {i}: {sorted(need - have)[:5]} not carried"
        touching += bool(need)
        rebuilds += i > 0 and not np.array_equal(qs[i], qs[i - 1])
    assert rebuilds >= 1 and touching >= 10


# --------------------------------------------------------------------------- the pile scene


@pytest.mark.slow
def test_plush_pile_scene_simulates_and_renders(tmp_path):
    from jaxplush import cli
    path = os.path.join(ROOT, "scenes", "plush_pile.obj")
    scene = jaxplush.load_scene(path)
    assert scene.n_objects == 3 and scene.floor is not None and scene.floor_friction > 0
    out = tmp_path / "pile.h5"
    assert cli.main(["simulate", path, "--steps", "20", "--dt", "1e-4", "--save-every", "10",
                     "--out", str(out), "--quiet"]) == 0
    gif = tmp_path / "pile.gif"
    assert cli.main(["render", str(out), "--out", str(gif), "--max-frames", "2"]) == 0
    assert gif.stat().st_size > 0


@pytest.mark.slow
def test_plush_pile_holds_and_comes_to_rest():
    """The pile scene as written, 2 s: each cushion stays on the one below, the stack comes to rest,
    no NaN, no vertex of one cushion more than 1 mm inside another (the independent inside test).
    About 40-90 s (three 642-vertex cushions in contact, capacity 642), hence slow."""
    path = os.path.join(ROOT, "scenes", "plush_pile.obj")
    scene = jaxplush.load_scene(path)
    dt, every = 1e-4, 100
    traj = jaxplush.simulate(scene, steps=20000, dt=dt, save_every=every)
    pos = traj.positions
    assert np.isfinite(pos).all()
    objs = [pos[:, o.vertex_slice[0]:o.vertex_slice[1]] for o in scene.objects]   # bottom to top
    end = [x[-1] for x in objs]
    assert end[0][:, 1].min() > scene.floor - 1e-6
    for lower, upper in zip(end, end[1:]):
        height = np.ptp(lower[:, 1])
        # the upper cushion rests on the lower one: its lowest point near the lower one's top, well
        # above the lower one's lowest point, and its centre over the lower one's footprint
        assert upper[:, 1].min() > lower[:, 1].min() + 0.8 * height
        assert abs(upper[:, 1].min() - lower[:, 1].max()) < 0.02
        centre = upper.mean(0)
        half = 0.5 * np.ptp(lower[:, [0, 2]], axis=0)
        assert np.all(np.abs(centre[[0, 2]] - lower.mean(0)[[0, 2]]) < 0.25 * half)
    # at rest: the largest vertex speed over the last 0.1 s (frame differences), against about
    # 0.5 m/s while the cushions inflate and land
    speed = np.linalg.norm(np.diff(pos[-11:], axis=0), axis=2).max(axis=1) / (every * dt)
    assert speed.max() < 0.02, speed
    frames = list(range(0, len(pos), 20)) + [len(pos) - 1]
    assert max(max_penetration(scene, pos[i]) for i in frames) <= 1e-3


@pytest.mark.heavy
def test_small_cushion_pile_holds_and_settles(tmp_path):
    """The pile scene at small size (162-vertex cushions, dt 2.5e-4, nmol calibrated by make_scenes for
    these meshes), 2 s: the stack keeps its order, settles, no NaN, no penetration beyond 1 mm."""
    from jaxplush.scene import write as scene_writer
    from jaxplush.model.mesh import superellipsoid
    objs, y = [], 0.002
    for name, a, c, nmol in (("bottom", 0.12, 0.05, 5.586e-4), ("middle", 0.09, 0.04, 4.266e-4),
                             ("top", 0.065, 0.03, 2.622e-4)):
        v, f = superellipsoid(a, c, 4, subdivisions=2)
        objs.append(dict(name=name, vertices=v, faces=f, total_weight=0.1, k_structural=800.0, nmol=nmol,
                         dashpot=0.2485, drag=5.0, translate=(0.0, y + c, 0.0)))
        y += 2 * c + 0.02
    path = tmp_path / "small_pile.obj"
    scene_writer.write_scene(path, objs, gravity=(0, -9.81, 0), floor=0.0, floor_friction=0.6,
                             contact_friction=0.6, contact_capacity=162)
    scene = jaxplush.load_scene(path)
    dt, every = 2.5e-4, 40
    pos = jaxplush.simulate(scene, steps=8000, dt=dt, save_every=every).positions
    assert np.isfinite(pos).all()
    end = [pos[-1, o.vertex_slice[0]:o.vertex_slice[1]] for o in scene.objects]
    for lower, upper in zip(end, end[1:]):
        assert upper[:, 1].min() > lower[:, 1].min() + 0.8 * np.ptp(lower[:, 1])
        assert abs(upper[:, 1].min() - lower[:, 1].max()) < 0.03
        assert np.all(np.abs(upper.mean(0)[[0, 2]] - lower.mean(0)[[0, 2]]) < 0.01)
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=2).max(axis=1) / (every * dt)
    # the coarse cushions settle less completely than the scene's (about 2 cm/s left at 2 s, against
    # about 0.7 m/s while they inflate and land)
    assert speed[-10:].max() < 0.05 and speed[-10:].max() < 0.1 * speed.max()
    assert max(max_penetration(scene, pos[i]) for i in range(0, len(pos), 20)) <= 1e-3


@pytest.mark.parametrize("caps,counts", [((60, 60), (51, 40)), ((60, 60), (69, 70)), ((130, 100), (100, 1)),
                                         ((200, 200), (150, 130))])
def test_tiled_nearest_search_equals_the_whole_table(caps, counts):
    """The nearest-candidate search builds its distance tables in tiles, only those within the
    counts: the same nearest vertices as the whole table, for counts below and above (an
    overflow) the capacities."""
    rng = np.random.default_rng(sum(caps) + sum(counts))
    (cap_a, cap_b), (n_a, n_b) = caps, counts
    pa = tuple(jnp.asarray(rng.normal(size=cap_a), jnp.float32) for _ in range(3))
    pb = tuple(jnp.asarray(rng.normal(size=cap_b), jnp.float32) for _ in range(3))
    ja, jb = jax.jit(contact._nearest_tiled)(pa, pb, jnp.int32(n_a), jnp.int32(n_b))
    pa, pb = np.stack(pa), np.stack(pb)
    m_a, m_b = min(n_a, cap_a), min(n_b, cap_b)
    d2 = np.sum((pa[:, :m_a, None] - pb[:, None, :m_b]) ** 2, axis=0)          # (m_a, m_b)
    # the nearest distance (an index may differ on a near-tie: the packed keys drop the lowest bits)
    jb, ja = np.asarray(jb)[:m_a], np.asarray(ja)[:m_b]
    assert jb.max() < m_b and ja.max() < m_a
    np.testing.assert_allclose(d2[np.arange(m_a), jb], d2.min(axis=1), rtol=1e-4)
    np.testing.assert_allclose(d2[ja, np.arange(m_b)], d2.min(axis=0), rtol=1e-4)
