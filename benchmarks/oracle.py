"""The recovery benchmark's oracle: which parameters a target determines, computed at the truth,
independent of the fitter (``bench_recovery.py --random N --seed S --oracle-only``).

For one random case (``jaxplush.fitting.targets.scenarios.draw_case``) and its target (the frames the
benchmark fits), the oracle gives the Cramér-Rao standard deviation of each fitted parameter's
logarithm (a relative error), from a Fisher information built on **segments restarted from the
true states**:

* the truth is rolled out in float64 (a float64 twin of the float32 target), keeping the full
  state (positions and velocities) at every saved frame;
* a float32 twin is started from each true state and compared with the truth frame by frame.
  Its distance after one frame is the float32 model's rounding; how far it goes before it
  drifts is how long a float32 simulation can follow the data;
* the horizon is cut into segments, each restarted from the true state at its first frame:

  - exact positions: one frame interval each (15-200 steps). The measurement noise of a
    coordinate is the rounding of one frame, per object (what a float32 fit cannot resolve);
  - point clouds (``n_points`` per frame, uniform by area, ``noise`` m per coordinate): as long
    as the float32 twin stays within half the noise (every object) and has grown by at most
    :data:`GROWTH` times its first frame's distance, so that information which builds up over
    many frames (a drag's, a damping's) counts, but chaos (a stack that settles, where rounding
    is amplified, and the sensitivities with it) cannot inflate it. A point measures the surface's displacement along
    its normal only: a frame's information is (n_points / area) sum_v area_v (n_v . J_v)^T
    (n_v . J_v) / (noise² + d²), with the true surface's vertex areas and normals there and d
    the twin's drift at that frame;

* along each segment the sensitivities J = d x / d log(p) are propagated in forward mode in
  float64 (one tangent per fitted parameter of each object), and F = sum of J^T W J over the
  frames. sd(log p_j) = sqrt((F^-1)_jj); directions of F scaled to a unit diagonal below
  :data:`NULL_EIG` of its largest eigenvalue are null (no data move them): a parameter with
  weight in them has an infinite sd (:func:`sds`).

A parameter is **determinable** when its sd is at most half the benchmark's tolerance (1% for
positions, 3% for clouds). The report's ``damping`` and air ``drag`` of one object decay every
velocity alike (only their combined rate 1/(D dt) + drag is determined); for such a pair the
oracle also gives the sd of the log of that rate, and the case is judged on the rate in place of
the pair. A case is determinable when each of its judged quantities is.

The bound takes the node states as known and is local (the data's information at the truth),
so a determinable case is one the data allow, not one a particular fitter finds easy. The oracle
shares no code with the fitter: it uses the simulator's step and JAX's forward mode only.
"""

from __future__ import annotations

import math

import numpy as np

#: Eigenvalues of F below this fraction of the largest are null directions (float64 J).
NULL_EIG = 1e-13
#: A parameter with more than this squared weight in the null directions has an infinite sd.
NULL_WEIGHT = 1e-10
#: A cloud's segment also ends where the float32 twin's distance from the truth (its largest over
#: the objects) has grown this many times over its first frame's: rounding amplified that much is
#: chaos, which would amplify the sensitivities as much. Over whole trajectories (50 frames), the
#: positions cases among seed 601's first 27 grew it 20-180x in most cases, and 3,000-100,000x in a
#: few (objects on a floor: a stack, a torus with friction).
GROWTH = 1000.0


def _labels(case):
    return [f"{n}[{o['name']}]" for n in case["params"] for o in case["objects"]]


def saved_steps(steps, every):
    """The target's saved steps (``jaxplush.fitting.targets.make_target``): 0, every, ..., steps."""
    saved = list(range(0, int(steps) + 1, int(every)))
    if saved[-1] != int(steps):
        saved.append(int(steps))
    return saved


def _vertex_normals_areas(x, faces):
    """(V, 3) unit vertex normals (area-weighted) and (V,) vertex areas (a third of each face's)."""
    from jaxplush.model.mesh import face_area_normals
    cr = face_area_normals(x, faces)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    nv = np.zeros_like(x)
    av = np.zeros(len(x))
    for k in range(3):
        np.add.at(nv, faces[:, k], cr)
        np.add.at(av, faces[:, k], area / 3.0)
    nv /= np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-300)
    return nv, av


def _machinery(scene, case, dt):
    """(sim, scene params, params_at(theta), advance(p, s, n)) at the current precision."""
    import jax
    import jax.numpy as jnp
    import jaxplush

    sim = jaxplush.make_simulator(scene, dt)
    p0 = sim.params()
    names = list(case["params"])
    n_obj = len(case["objects"])

    def params_at(theta):
        fields = p0._asdict()
        for i, n in enumerate(names):
            fields[n] = fields[n] * jnp.exp(theta[i * n_obj:(i + 1) * n_obj])
        return type(p0)(**fields)

    def advance(p, s, n):
        return jax.lax.fori_loop(0, n, lambda _, c: sim.internal.step(p, c, None), s)

    return sim, p0, params_at, advance


def truth_states(scene, case, dt, saved):
    """The float64 truth's internal states ((x, v) as (3, V) numpy arrays) at every saved step."""
    import jax
    sim, p, _, advance = _machinery(scene, case, dt)
    assert sim.dtype == np.float64, "truth_states needs jax_enable_x64"
    s = sim.internal.to_internal(sim.init_fn(p))
    run = {}
    out = [tuple(np.asarray(c) for c in s)]
    for a, b in zip(saved, saved[1:]):
        n = b - a
        if n not in run:
            run[n] = jax.jit(lambda p, s, n=n: advance(p, s, n))
        s = run[n](p, s)
        out.append(tuple(np.asarray(c) for c in s))
    return out


def _object_rms(d, obj_of_vertex, n_obj):
    """(O,) RMS per object of a (3, V) difference."""
    sq = np.bincount(obj_of_vertex, weights=np.sum(d ** 2, axis=0), minlength=n_obj)
    cnt = np.bincount(obj_of_vertex, minlength=n_obj) * 3
    return np.sqrt(sq / np.maximum(cnt, 1))


def twin_segments(scene, case, dt, saved, states, obj_of_vertex, threshold):
    """Segments restarted from the true states, each as long as the float32 twin started there
    stays within ``threshold`` (RMS m, every object) of the float64 truth and within
    :data:`GROWTH` times its distance after the segment's first frame (one frame at least).

    Returns (segments [(first frame, last frame)], divergence (T, O): the twin's RMS per object at
    every frame > 0 within its segment). Needs ``jax_enable_x64`` off."""
    import jax
    import jax.numpy as jnp
    sim, p, _, advance = _machinery(scene, case, dt)
    assert sim.dtype == np.float32, "twin_segments needs jax_enable_x64 off"
    n_obj = len(case["objects"])
    State = type(sim.internal.to_internal(sim.init_fn(p)))
    run = {}

    def step(s, k):
        n = saved[k] - saved[k - 1]
        if n not in run:
            run[n] = jax.jit(lambda p, s, n=n: advance(p, s, n))
        return run[n](p, s)

    T = len(saved)
    div = np.zeros((T, n_obj))
    segments = []
    r = 0
    while r < T - 1:
        s = State(*(jnp.asarray(c, jnp.float32) for c in states[r]))
        k = r
        while k < T - 1:
            s = step(s, k + 1)
            d = _object_rms(np.asarray(s.x, np.float64) - states[k + 1][0], obj_of_vertex, n_obj)
            if k == r:
                first = max(float(d.max()), 1e-300)      # the twin's distance after one frame
            elif float(d.max()) > threshold or float(d.max()) > GROWTH * first:
                break
            div[k + 1] = d
            k += 1
        segments.append((r, k))
        r = k
    return segments, div


def segment_information(scene, case, dt, saved, states, segments, weight, cloud=None):
    """F (P, P) of the log parameters: forward sensitivities of the float64 truth along every
    segment (restarted from the true state at its first frame), at every frame after the first.

    ``weight(frame)``: (V,) inverse noise variance of each vertex at that frame. ``cloud``: None
    (exact positions: every coordinate measured) or points per frame (normal displacements of
    the surface only, uniform by area). Needs ``jax_enable_x64``."""
    import jax
    import jax.numpy as jnp
    sim, p0, params_at, advance = _machinery(scene, case, dt)
    assert sim.dtype == np.float64
    State = type(sim.internal.to_internal(sim.init_fn(p0)))
    P = len(case["params"]) * len(case["objects"])
    theta0 = jnp.zeros((P,), jnp.float64)
    eye = jnp.eye(P, dtype=jnp.float64)
    faces = np.asarray(scene.faces, np.int64)
    run = {}

    def sens(n):
        if n not in run:
            def go(s, ds):
                def adv(theta, s):
                    return advance(params_at(theta), s, n)

                def tangent(e, d):
                    return jax.jvp(adv, (theta0, s), (e, d))[1]
                return adv(theta0, s), jax.vmap(tangent)(eye, ds)
            run[n] = jax.jit(go)
        return run[n]

    F = np.zeros((P, P))
    for a, b in segments:
        s = State(*(jnp.asarray(c) for c in states[a]))
        ds = State(*(jnp.zeros((P,) + np.shape(c), jnp.float64) for c in states[a]))
        for k in range(a + 1, b + 1):
            s, ds = sens(saved[k] - saved[k - 1])(s, ds)
            J = np.asarray(ds.x)                       # (P, 3, V)
            w = weight(k)
            if cloud is None:
                Jf = J.reshape(P, 3, -1) * np.sqrt(w)[None, None, :]
                Jf = Jf.reshape(P, -1)
                F += Jf @ Jf.T
            else:
                nv, av = _vertex_normals_areas(states[k][0].T, faces)
                Jn = np.einsum("vc,pcv->pv", nv, J)
                F += (cloud / av.sum()) * (Jn * (av * w)[None, :]) @ Jn.T
    return F


def sds(F, directions):
    """sd of each linear combination g (rows of ``directions``, (K, P)) of the log parameters:
    sqrt(g^T F^-1 g); infinite when g has weight in F's null directions.

    F is first scaled to unit diagonal (S F S, S = diag(F)^-1/2), so that a parameter the data
    fix a million times better than another does not make the other's directions look null: a
    null direction is one of no information relative to the parameters it mixes, not relative
    to the best-determined parameter of the scene. A parameter with no information at all (a zero
    diagonal) has an infinite sd."""
    F = 0.5 * (F + F.T)
    d = np.diag(F).copy()
    dead = ~(d > 0)
    s = np.where(dead, 0.0, 1.0 / np.sqrt(np.where(dead, 1.0, d)))
    C = F * s[:, None] * s[None, :]
    C[dead, dead] = 1.0                     # a placeholder: directions on it are infinite (below)
    w, Q = np.linalg.eigh(C)
    top = max(float(w[-1]), 1e-300)
    null = w <= NULL_EIG * top
    out = []
    for g in np.atleast_2d(directions):
        g = np.asarray(g, np.float64)
        if np.any(g[dead] != 0):
            out.append(math.inf)
            continue
        c = Q.T @ (g * s)                   # g^T F^-1 g = (S g)^T C^-1 (S g)
        if float(np.sum(c[null] ** 2)) > NULL_WEIGHT * float(np.sum(c ** 2)):
            out.append(math.inf)
        else:
            out.append(float(math.sqrt(np.sum(c[~null] ** 2 / w[~null]))))
    return out


def judge(sd, rate_sd, tolerance):
    """Per-quantity determinability and the case's verdict: (determinable {label: bool},
    case_determinable, reason or None). Damping+drag pairs are judged on their combined rate."""
    half = tolerance / 2
    det = {lab: bool(s <= half) for lab, s in sd.items()}
    judged = dict(det)
    for lab, s in rate_sd.items():
        name = lab[len("rate["):-1]
        judged.pop(f"damping[{name}]", None)
        judged.pop(f"drag[{name}]", None)
        judged[lab] = bool(s <= half)
    bad = [lab for lab, ok in judged.items() if not ok]
    allsd = {**sd, **rate_sd}
    reason = None if not bad else "; ".join(
        f"{lab} sd {100 * allsd[lab]:.3g}% > {100 * half:g}%" for lab in bad)
    return judged, not bad, reason


def oracle_case(scene, case, *, dt, steps, every, kind, n_points=None, noise=0.0, tolerance, target=None):
    """The oracle of one case (a dict: labels, sd, rate_sd, rounding, determinable, case
    determinable, reason, segments, frames, fisher: F as a list of rows; with the ``target`` (:class:`jaxplush.fitting.targets.Target`)
    also ``twin_rms``, :func:`frame_rms` of the float64 truth). The float64 parts run under ``jax.enable_x64(True)``,
    the float32 twin under ``jax.enable_x64(False)``, whatever the caller's precision."""
    import jax
    saved = saved_steps(steps, every)
    labels = _labels(case)
    obj_of_vertex = np.zeros(scene.n_vertices, np.int64)
    for j, o in enumerate(scene.objects):
        obj_of_vertex[o.vertex_slice[0]:o.vertex_slice[1]] = j
    precision = getattr(jax, "enable_x64", None)
    if precision is None:                       # jax < 0.6
        from jax.experimental import enable_x64 as precision
    with precision(True):
        states = truth_states(scene, case, dt, saved)
    with precision(False):
        # the float32 twin: one frame from each true state (its rounding), then segments as long as
        # it stays within half the measurement noise (clouds); exact positions: one frame each
        _, div1 = twin_segments(scene, case, dt, saved, states, obj_of_vertex, threshold=0.0)
        if kind == "points":
            segments, div = twin_segments(scene, case, dt, saved, states, obj_of_vertex, threshold=noise / 2)
        else:
            segments, div = [(r, r + 1) for r in range(len(saved) - 1)], div1
    rounding = float(np.sqrt(np.mean(div1[1:] ** 2)))
    base = noise ** 2 if kind == "points" else 0.0
    floor = max(rounding, 1e-300) ** 2

    def weight(k):
        return 1.0 / (base + np.maximum(div[k] ** 2, floor))[obj_of_vertex]

    with precision(True):
        F = segment_information(scene, case, dt, saved, states, segments, weight,
                                cloud=int(n_points) if kind == "points" else None)
    P = len(labels)
    sd = dict(zip(labels, sds(F, np.eye(P))))
    rate_sd = {}
    if "damping" in case["params"] and "drag" in case["params"]:
        from jaxplush.fitting.stages.equation_error import damping_rate
        from jaxplush.fitting.targets.scenarios import case_truth
        truth = case_truth(case)
        for j, o in enumerate(case["objects"]):
            rate_d, g = float(damping_rate(truth["damping"][j], dt)), truth["drag"][j]   # 1/(D dt), drag
            r = rate_d + g
            grad = np.zeros(P)                  # d log r / d log D, d log r / d log drag
            grad[labels.index(f"damping[{o['name']}]")] = -rate_d / r
            grad[labels.index(f"drag[{o['name']}]")] = g / r
            rate_sd[f"rate[{o['name']}]"] = sds(F, grad[None])[0]
    judged, ok, reason = judge(sd, rate_sd, tolerance)
    out = dict(labels=labels, sd=sd, rate_sd=rate_sd, rounding=rounding,
               determinable=judged, case_determinable=ok, reason=reason,
               segments=len(segments), frames=len(saved) - 1, fisher=F.tolist())
    if target is not None:
        truth_frames = np.stack([x.T for x, *_ in states[1:]])
        out["twin_rms"] = [float(r) for r in frame_rms(truth_frames, target, np.asarray(scene.faces, np.int64))]
    return out


def frame_rms(frames, target, faces):
    """(T,) RMS misfit of simulated ``frames`` (T, V, 3) to the target at each of its frames: of
    the coordinates for positions, of the points' distances to the simulated surface for clouds.
    Frames fewer than the target's (a fit cut at a predictable horizon) are the target's first.

    The measure of the acceptance for several objects in contact: the frames re-simulated at
    the fitted values against those of the truth's float64 twin (the oracle's ``twin_rms``)."""
    frames = np.asarray(frames, np.float64)
    if getattr(target, "positions", None) is not None:
        return np.sqrt(np.mean((frames - np.asarray(target.positions, np.float64)[:len(frames)]) ** 2, axis=(1, 2)))
    import jax
    import jax.numpy as jnp
    from jaxplush.fitting.objective.losses import point_surface_distance2, vertex_faces
    vf = vertex_faces(faces, frames.shape[1])
    one = jax.jit(lambda x, p: jnp.sqrt(jnp.mean(point_surface_distance2(x, p, faces, vf))))
    return np.array([float(one(x, p)) for x, p in zip(frames, np.asarray(target.points, np.float64))])
