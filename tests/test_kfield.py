"""Spring stiffness per edge (``Params.k_structural`` of shape (E,); scene keywords ``g``,
``k_region``, ``k_edge``): the field acts as the per-object value where it is uniform, its forces
are minus its energy's gradient, a stiff region stretches less than a soft one, the gradients of
every method match finite differences, the scene format reads and writes it, and the engines that
take one k per object refuse it or bound it by the stiffest edge, and the batched engine runs
one field per point."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush import SceneError
from jaxplush.stepping import batched
from jaxplush.fitting.objective import gradients as G
from jaxplush.model import forces as model
from jaxplush.model import layout
from jaxplush.scene.write import format_scene, stiffness_keys
from jaxplush.stepping import stability
from conftest import assert_gradient_matches_fd, icosphere_text

DT = 2e-4


def _field(sim, rng, lo=0.5, hi=1.5):
    """A random (E,) field around each edge's object's k."""
    k = np.asarray(sim.scene.params.k_structural, np.float64)[sim.topology.edge_object]
    return k * rng.uniform(lo, hi, sim.topology.n_edges)


def _two_balls(**kw):
    """Two icospheres 1 cm apart (within the contact thickness: contact pushes from the start)."""
    return jaxplush.parse_scene(icosphere_text(1, **kw) + icosphere_text(1, name="b", translate=(0.21, 0, 0),
                                                                         offset=42, header=False, k=300.0), "<two>")


def _halves(k_soft, k_stiff, subdivisions=2, hang=True):
    """An icosphere whose faces left of x = 0 form group 'stiff' (k_region k_stiff) and the rest
    group 'soft' (the object's k_structural k_soft), hung from its top vertices."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    left = v[f].mean(axis=1)[:, 0] < 0
    out = ["o ball", f"k_structural {k_soft!r}", "total_weight 0.2", "drag 20", f"k_region stiff {k_stiff!r}"]
    out += [f"v {a!r} {b!r} {c!r}" for a, b, c in v.tolist()]
    out += ["g stiff"] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f[left].tolist()]
    out += ["g soft"] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f[~left].tolist()]
    if hang:
        out += [f"fixed {i + 1}" for i in np.nonzero(v[:, 1] > 0.09)[0].tolist()]
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- forward model

@pytest.mark.parametrize("integrator,assembly", [("verlet", "ring"), ("verlet", "segment"),
                                                 ("implicit_euler", "ring"), ("mesit", "ring")])
def test_uniform_field_matches_the_per_object_value(integrator, assembly):
    """A field equal to each object's k everywhere gives the per-object rollout, to rounding
    (two objects in contact, gas, dashpot and drag: every place that reads k)."""
    scene = _two_balls(nmol=1e-3, dashpot=0.05, drag=0.5)
    sim = jaxplush.make_simulator(scene, DT, integrator=integrator, assembly=assembly)
    p = sim.params()
    pf = p._replace(k_structural=jnp.asarray(np.asarray(p.k_structural)[sim.topology.edge_object], sim.dtype))
    assert layout.is_field(sim.topology, pf.k_structural) and not layout.is_field(sim.topology, p.k_structural)
    s0 = sim.init_fn(p)
    a, fa, _ = jaxplush.rollout(sim, p, s0, 4, 25)
    b, fb, _ = jaxplush.rollout(sim, pf, s0, 4, 25)
    assert float(jnp.linalg.norm(fa[-1] - fa[0])) > 1e-4          # it moved
    scale = float(jnp.linalg.norm(fa))
    assert float(jnp.linalg.norm(fb - fa)) <= 1e-5 * scale, float(jnp.linalg.norm(fb - fa)) / scale


@pytest.mark.parametrize("assembly", ["ring", "segment"])
def test_field_force_is_minus_the_energy_gradient(x64, assembly):
    """f = -dU/dx with a random field (springs and gas; float64, jax.grad of potential_energy),
    at a random deformation."""
    scene = jaxplush.parse_scene(icosphere_text(1, nmol=1e-3), "<gas>")
    sim = jaxplush.make_simulator(scene, DT, assembly=assembly)
    rng = np.random.default_rng(0)
    p = sim.params()._replace(k_structural=jnp.asarray(_field(sim, rng, 0.2, 3.0)))
    x = jnp.asarray(sim.topology.x0 * 1.05 + 3e-3 * rng.standard_normal(sim.topology.x0.shape))
    f, _ = sim.force_fn(p, x, jnp.zeros_like(x))
    g = jax.grad(lambda y: model.potential_energy(sim.topology, p, y, scene.temperature))(x)
    assert float(jnp.linalg.norm(f + g)) <= 1e-11 * float(jnp.linalg.norm(g))
    # and the field is not a disguised per-object value: the uniform mean gives other forces
    pm = p._replace(k_structural=layout.object_stiffness(sim.topology, p.k_structural))
    fm, _ = sim.force_fn(pm, x, jnp.zeros_like(x))
    assert float(jnp.linalg.norm(fm - f)) > 0.05 * float(jnp.linalg.norm(f))


def test_stiff_half_stretches_less_under_a_hanging_load():
    """An icosphere hung from its top vertices, its left half ten times stiffer: the left half's
    springs stretch about ten times less and its vertices sag less; with equal halves both sides
    stretch alike (the control)."""
    out = {}
    for k_stiff in (2000.0, 200.0):
        scene = jaxplush.parse_scene(_halves(200.0, k_stiff), "<halves>")
        assert scene.has_k_field
        x = jaxplush.simulate(scene, 3000, 1e-4).positions[-1]
        x0, e = scene.vertices, scene.edges
        strain = np.abs(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
                        / np.linalg.norm(x0[e[:, 0]] - x0[e[:, 1]], axis=1) - 1.0)
        a = scene.region_edges()
        inside = {g: a[:, scene.group_names.index(g)] == 1.0 for g in ("stiff", "soft")}
        sag = x[:, 1] - x0[:, 1]
        out[k_stiff] = dict(stiff=strain[inside["stiff"]].mean(), soft=strain[inside["soft"]].mean(),
                            sag_left=sag[x0[:, 0] < -0.01].mean(), sag_right=sag[x0[:, 0] > 0.01].mean())
    r = out[2000.0]
    assert r["soft"] > 5.0 * r["stiff"], r
    assert r["sag_right"] < 2.0 * r["sag_left"] < 0, r                # sags (y falls) more on the soft side
    c = out[200.0]
    assert abs(c["soft"] - c["stiff"]) < 0.1 * c["soft"], c
    assert abs(c["sag_right"] - c["sag_left"]) < 0.01 * abs(c["sag_left"]), c
    # the stiff half stretches less than the same half of the uniform ball, the soft half more
    assert r["stiff"] < c["stiff"] and r["soft"] > c["soft"], (r, c)


# --------------------------------------------------------------------------- gradients

@pytest.mark.parametrize("case", ["gas", "contact"])
@pytest.mark.parametrize("method", ["adjoint", "checkpoint"])
def test_field_gradient_matches_finite_differences(x64, method, case):
    """d loss / d k_field (shape (E,)) from rollout_loss: central differences at two step sizes
    along a few random edges (float64, log-parameters), and jax.grad of plain autodiff."""
    if case == "gas":
        scene = jaxplush.parse_scene(icosphere_text(1, nmol=1e-3, dashpot=0.05, drag=0.5, damping=500.0), "<g>")
    else:
        scene = _two_balls(gravity=(0.0, 0.0, 0.0))
    sim = jaxplush.make_simulator(scene, DT)
    assert G.adjoint_supported(sim)
    rng = np.random.default_rng(1)
    p = sim.params()._replace(k_structural=jnp.asarray(_field(sim, rng)))
    s0 = sim.init_fn(p)
    frames = (10, 30, 60)
    target = jnp.asarray(sim.topology.x0[None] + 2e-3 * rng.standard_normal((3, sim.topology.n_vertices, 3)))

    def loss(x, t):
        return jnp.sum((x - t) ** 2)

    def f(q, m=method):
        return G.rollout_loss(sim, q, s0, frames, loss, target, method=m, segment=7)

    g = jax.jit(jax.grad(f))(p)
    assert g.k_structural.shape == (sim.topology.n_edges,)
    ref = jax.jit(jax.grad(lambda q: f(q, "plain")))(p)
    for a, b in zip(g, ref):
        assert float(jnp.linalg.norm(a - b)) <= 1e-9 * float(jnp.linalg.norm(b)) + 1e-300
    theta0 = np.log(np.asarray(p.k_structural))
    fj = jax.jit(lambda th: f(p._replace(k_structural=jnp.exp(th))))
    edges = rng.choice(sim.topology.n_edges, 4, replace=False)
    dirs = np.eye(sim.topology.n_edges)[edges]
    dtheta = np.asarray(g.k_structural)[edges] * np.exp(theta0[edges])      # d loss / d log k_e
    assert np.all(dtheta != 0)
    assert_gradient_matches_fd(lambda th: float(fj(jnp.asarray(th))), theta0, dtheta, h=1e-4, rtol=1e-6,
                               directions=dirs)


# --------------------------------------------------------------------------- scene format

def _grouped_text(extra=(), first_face_edge=False):
    """icosphere_text(1) with its faces in two groups 'top' and 'rest' (lines after the 'o')."""
    lines = icosphere_text(1).splitlines()
    faces = [i for i, ln in enumerate(lines) if ln.startswith("f ")]
    lines.insert(faces[len(faces) // 2], "g rest")
    lines.insert(faces[0], "g top")
    end = lines.index("END_OBJECT")
    return "\n".join(lines[:end] + list(extra) + lines[end:]) + "\n", lines


def _first_face(lines):
    return [int(t) for t in next(ln for ln in lines if ln.startswith("f ")).split()[1:]]


def test_regions_and_edges_build_the_field():
    text, lines = _grouped_text()
    plain = jaxplush.parse_scene(text, "<g>")
    assert not plain.has_k_field and plain.params.k_structural.tolist() == [100.0]   # groups alone change nothing
    assert plain.group_names == ("top", "rest") and set(plain.face_groups.tolist()) == {0, 1}
    a, b, _ = _first_face(lines)
    scene = jaxplush.parse_scene(_grouped_text(("k_region top 400", f"k_edge {b} {a} 7.5"))[0], "<g>")
    assert scene.has_k_field and scene.params.k_structural.shape == (len(scene.edges),)
    k = scene.params.k_structural
    share = scene.region_edges()
    np.testing.assert_array_equal(share.sum(axis=1) <= 1, True)
    top = share[:, 0]
    e = int(np.nonzero((scene.edges == sorted((a - 1, b - 1))).all(axis=1))[0][0])
    assert k[e] == 7.5                                                   # k_edge overrides, either order
    rest = np.arange(len(k)) != e
    np.testing.assert_array_equal(k[rest], (400.0 * top + 100.0 * (1 - top))[rest])
    assert set(np.unique(k[rest]).tolist()) == {100.0, 250.0, 400.0}   # inside, on the border, outside
    # the same field from traced values (a fit per region), and from other region values
    kj = scene.stiffness_field(k_region=jnp.asarray([400.0, np.nan]), xp=jnp)
    np.testing.assert_allclose(np.asarray(kj), k, rtol=1e-6)
    k2 = scene.stiffness_field(k_region=[400.0, 50.0])
    assert set(np.unique(k2[rest]).tolist()) == {50.0, 225.0, 400.0}


def test_g_keeps_naming_objects_without_o():
    """Before an object's 'o' (or without 'o'), 'g' names the object as it always did; after it,
    'g' starts a face group and never renames or splits the object."""
    body = "\n".join(ln for ln in icosphere_text(1).splitlines()[1:] if not ln.startswith(("o ", "END")))
    s1 = jaxplush.parse_scene("g named\n" + body + "\n", "<g1>")
    assert s1.object_names == ("named",) and s1.group_names == () and (s1.face_groups == -1).all()
    s2 = jaxplush.parse_scene("o ball\ng part\n" + body + "\n", "<g2>")
    assert s2.object_names == ("ball",) and s2.group_names == ("part",) and (s2.face_groups == 0).all()
    # a bare 'g' ends the group
    lines = ("o ball\ng part\n" + body).splitlines()
    faces = [i for i, ln in enumerate(lines) if ln.startswith("f ")]
    lines.insert(faces[5], "g")
    s3 = jaxplush.parse_scene("\n".join(lines) + "\n", "<g3>")
    assert s3.face_groups.tolist() == [0] * 5 + [-1] * (len(faces) - 5)


@pytest.mark.parametrize("extra,match", [
    (("k_region nowhere 5",), "object 'ball' has no face group 'nowhere'"),
    (("k_region top -1",), "'k_region' -1 must be >= 0"),
    (("k_region top",), "'k_region' expects a face group name and a stiffness"),
    (("k_region top 5", "k_region top 6"), "given twice"),
    (("k_edge 1 2 -3",), "'k_edge' -3 must be >= 0"),
    (("k_edge 1 2",), "'k_edge' expects 2 vertex indices and a stiffness"),
    (("k_edge 1 1 3",), "not joined by an edge"),
    (("k_edge 1 999 3",), "'k_edge' vertex 999 is not a vertex of object 'ball'"),
])
def test_stiffness_keywords_errors_name_file_and_line(extra, match):
    text, _ = _grouped_text(extra)
    with pytest.raises(SceneError, match=match) as info:
        jaxplush.parse_scene(text, "ball.obj")
    lines = text.splitlines()
    assert info.value.path == "ball.obj"
    assert info.value.line == len(lines) - lines[::-1].index(extra[-1])     # the (last) offending line


def test_k_edge_between_vertices_that_share_no_edge():
    text, lines = _grouped_text()
    faces = np.asarray([[int(t) for t in ln.split()[1:]] for ln in lines if ln.startswith("f ")])
    scene = jaxplush.parse_scene(text, "<g>")
    joined = {tuple(e) for e in (scene.edges + 1).tolist()}
    far = next((1, j) for j in range(2, faces.max() + 1) if (1, j) not in joined)
    bad = _grouped_text((f"k_edge {far[0]} {far[1]} 3",))[0]
    with pytest.raises(SceneError, match=f"vertices {far[0]} and {far[1]} are not joined by an edge") as info:
        jaxplush.parse_scene(bad, "ball.obj")
    assert info.value.line == bad.splitlines().index(f"k_edge {far[0]} {far[1]} 3") + 1


def _objects(scene, k=None):
    out = []
    for i, o in enumerate(scene.objects):
        a, b = o.vertex_slice
        fa, fb = o.face_slice
        d = dict(name=o.name, vertices=scene.vertices[a:b], faces=scene.faces[fa:fb] - a,
                 total_weight=float(scene.params.total_weight[i]))
        d.update(stiffness_keys(scene, i, k))
        out.append(d)
    return out


def test_write_parse_round_trip(tmp_path):
    """format_scene / write_scene write a field (groups, k_region, k_edge lines) that reads back
    bit for bit: the scene's own, and a random one, over two objects."""
    text, lines = _grouped_text(("k_region top 400", "k_edge {} {} 7.5".format(*_first_face(
        icosphere_text(1).splitlines())[:2])))
    second = icosphere_text(1, name="b", translate=(0.5, 0, 0), offset=42, header=False, k=300.0)
    scene = jaxplush.parse_scene(text + second, "<two>")
    assert scene.has_k_field
    out = format_scene(_objects(scene))
    assert sum(ln.startswith("k_edge") for ln in out.splitlines()) == 1       # compact: regions carry over
    assert "k_region top 400.0" in out.splitlines()
    back = jaxplush.parse_scene(out, "<back>")
    np.testing.assert_array_equal(back.params.k_structural, scene.params.k_structural)
    np.testing.assert_array_equal(back.face_groups, scene.face_groups)
    field = scene.params.k_structural * np.random.default_rng(2).uniform(0.5, 2.0, len(scene.edges)) / 3.0
    from jaxplush.scene.write import write_scene
    write_scene(tmp_path / "f.obj", _objects(scene, field))
    np.testing.assert_array_equal(jaxplush.load_scene(tmp_path / "f.obj").params.k_structural, field)
    # a per-object k writes no field (the groups stay)
    plain = jaxplush.parse_scene(format_scene(_objects(scene, [50.0, 60.0])), "<p>")
    assert plain.params.k_structural.tolist() == [50.0, 60.0] and plain.group_names == scene.group_names


def test_writer_checks_the_stiffness_keys():
    scene = jaxplush.parse_scene(_grouped_text()[0], "<g>")
    obj = _objects(scene)[0]
    with pytest.raises(ValueError, match="not one of its face groups"):
        format_scene([dict(obj, k_region={"nowhere": 1.0})])
    with pytest.raises(ValueError, match="one stiffness per edge"):
        format_scene([dict(obj, k_edge=np.ones(3))])
    with pytest.raises(ValueError, match="groups must name a group"):
        format_scene([dict(obj, groups=["top"])])


# --------------------------------------------------------------------------- engines and checks

def test_batched_engine_runs_a_field_per_point():
    """The batched engine takes the field (the scene's, shared, or one per point): each lane gives
    ``jaxplush.simulate``'s frames with that field, to float32 rounding relative to the motion; a
    per-object k spreads to the uniform field; a simulator built without the field refuses one."""
    scene = jaxplush.parse_scene("floor -0.101\n" + _grouped_text(("k_region top 400",))[0], "<g>")   # dropped
    terms = model.Terms.for_scene(scene)
    assert terms.k_field
    bsim = batched.make_batched_simulator(scene, DT, 3)
    assert bsim.terms.k_field
    rng = np.random.default_rng(3)
    sim = jaxplush.make_simulator(scene, DT)
    fields = [np.asarray(scene.params.k_structural, np.float64), _field(sim, rng), _field(sim, rng, 1.5, 3.0)]
    p = scene.params._replace(k_structural=np.stack(fields, axis=1))
    pb = bsim.params(p)
    assert pb.k_structural.shape == (len(scene.edges), 3)
    steps, every = 200, 50
    _, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb), steps // every, every,
                                        observe=batched.positions_observer)
    assert not np.asarray(health.failed).any()
    frames = np.asarray(frames, np.float64)
    for b, k in enumerate(fields):
        ref = jaxplush.simulate(scene, steps, DT, every, params=scene.params._replace(k_structural=k)).positions[1:]
        motion = np.linalg.norm(ref - scene.vertices)
        assert np.linalg.norm(frames[:, b] - ref) < 1e-5 * motion, b
    assert np.abs(frames[-1, 1] - frames[-1, 2]).max() > 1e-4                # the fields matter
    # the scene's field shared by every point, and a per-object k as the uniform field
    shared = bsim.params()
    np.testing.assert_array_equal(np.asarray(shared.k_structural), np.asarray(pb.k_structural[:, :1]).repeat(3, 1))
    uniform = bsim.params(scene.params._replace(k_structural=np.array([250.0])))
    np.testing.assert_array_equal(np.asarray(uniform.k_structural), 250.0)
    plain = jaxplush.parse_scene(icosphere_text(1), "<p>")
    bplain = batched.make_batched_simulator(plain, DT, 2)
    with pytest.raises(NotImplementedError, match="per-edge stiffness field"):
        bplain.params(plain.params._replace(k_structural=np.full(bplain.topology.n_edges, 100.0)))


def test_a_sweep_keeps_the_field_and_refuses_a_k_axis():
    from jaxplush.fitting.sweep import SweepError, sweep
    from jaxplush.fitting.targets import make_target
    scene = jaxplush.parse_scene("floor -0.101\n" + _grouped_text(("k_region top 400", "dashpot 0.01"))[0], "<g>")
    target = make_target(scene, 200, DT, 50)
    res = sweep(scene, {"total_weight": [0.04, 0.05, 0.07]}, steps=200, dt=DT, target=target, progress=False,
                batch=3)
    assert res.best()["total_weight"] == 0.05 and res.loss[1] < 1e-6 * min(res.loss[0], res.loss[2])
    with pytest.raises(SweepError, match="per-edge field"):
        sweep(scene, {"k": [100.0, 200.0]}, steps=10, dt=DT, progress=False)


def test_parameter_shapes_are_checked_before_tracing():
    scene = jaxplush.parse_scene(icosphere_text(1), "<p>")
    sim = jaxplush.make_simulator(scene, DT)
    bad = scene.params._replace(k_structural=np.ones(7))
    with pytest.raises(ValueError, match=r"k_structural has shape \(7,\); expected \(1,\) per object or \(120,\)"):
        sim.params(bad)
    p = sim.params()
    with pytest.raises(ValueError, match="parameter nmol has shape"):
        jaxplush.rollout(sim, p._replace(nmol=jnp.zeros(120)), sim.init_fn(p), 1)
    with pytest.raises(ValueError, match="k_structural has shape"):
        G.rollout_loss(sim, p._replace(k_structural=jnp.ones(5)), sim.init_fn(p), (1,), lambda x, a: jnp.sum(x),
                       jnp.zeros((1,)))


def test_stability_follows_the_stiffest_edge():
    """The closed-form bound and the power-iteration estimate follow the stiffest springs, not the
    mean: one stiff region (16x) or a few stiff edges cut the stable step by about 4x (sqrt 16)."""
    base = jaxplush.parse_scene(_halves(200.0, 200.0, subdivisions=1, hang=False), "<u>")
    sim = jaxplush.make_simulator(base, DT)
    p = sim.params()
    b0 = stability.bound(sim, p)
    b_all = stability.bound(sim, p._replace(k_structural=p.k_structural * 16.0))
    half = jaxplush.parse_scene(_halves(200.0, 3200.0, subdivisions=1, hang=False), "<h>")
    hsim = jaxplush.make_simulator(half, DT)
    b_half = stability.bound(hsim, hsim.params())
    assert b_all.dt_max <= b_half.dt_max <= 1.05 * b_all.dt_max, (b_all, b_half)
    assert b_half.dt_gershgorin == pytest.approx(b_all.dt_gershgorin)
    # a few stiff edges: the mean hardly moves, the limit does
    k = np.full(sim.topology.n_edges, 200.0)
    k[:3] = 3200.0
    pf = p._replace(k_structural=jnp.asarray(k, sim.dtype))
    assert layout.object_stiffness(sim.topology, k)[0] < 1.5 * 200.0
    b_few = stability.bound(sim, pf)
    assert b_few.dt_max < 0.5 * b0.dt_max, (b0, b_few)
    est0, est = stability.estimate(sim, p), stability.estimate(sim, pf)
    assert est.dt_max < 0.6 * est0.dt_max, (est0, est)
    assert b_few.dt_max <= est.dt_max                                   # the bound stays safe


def test_trajectory_keeps_a_large_field(tmp_path):
    """A run's field (here 1920 edges, beyond an HDF5 attribute's 64 KiB at 30,000) is saved as the
    dataset k_structural_field, the attribute k_structural then the objects' means; `jaxplush info`
    reports the field."""
    scene = jaxplush.parse_scene(_halves(200.0, 2000.0, subdivisions=3, hang=False), "<h>")
    traj = jaxplush.simulate(scene, 3, 1e-5)
    path = traj.save(tmp_path / "t.h5")
    back = jaxplush.load_trajectory(path)
    np.testing.assert_array_equal(back["k_structural_field"], scene.params.k_structural)
    mean = scene.params.k_structural.mean()
    assert back["attrs"]["k_structural"] == pytest.approx([mean], rel=1e-12)
    assert 200.0 < mean < 2000.0
    import contextlib
    import io
    from jaxplush import cli
    (tmp_path / "h.obj").write_text(scene.text)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["info", str(tmp_path / "h.obj")]) == 0
    assert f"k_structural {mean:g} N/m (mean of a per-edge field, 200–2000)" in out.getvalue()
