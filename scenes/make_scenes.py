#!/usr/bin/env python
"""Build the example scenes in this folder: ``python scenes/make_scenes.py``.

Writes ``ball_drop.obj``, ``bear.obj``, ``hanging.obj``, ``two_plushies.obj`` and ``plush_pile.obj`` next to
this script (atomically, through :func:`jaxplush.scene.write.write_scene`), prints a
parameter table per scene, then re-reads every file it wrote and checks it (closed,
consistently wound, positive volume with trimesh; then ``jaxplush.scene.parse.load_scene``).
The output is deterministic: rerunning gives byte-identical files.

Every number in the headers is computed here, not guessed (docs/model.md §4, §5, §8):

* ``nmol``: the free (gravity-free) inflated size ``s*`` is 1.05 x rest. For the
  icosphere balls it comes from ``k s (s-1) sum(L^2) = 3 nRT`` (§8 item 5), i.e.
  ``nmol = k sum(L^2) s (s-1) / (3 R T)``. That formula assumes uniform scaling is the
  equilibrium; the lobed bear instead gains volume by unfolding its creases (with the
  formula's nmol it swells to (V*/V0)^(1/3) = 1.16 and loses its shape), so its nmol is
  solved numerically for a measured (V*/V0)^(1/3) = 1.05 at the relaxed equilibrium.
  The pile's flat cushions (superellipsoids) are calibrated the same way: for them the
  formula's nmol is 4-6 times larger (see their headers) and would round them.
* ``dashpot`` ``c = zeta_spring * sqrt(2 k m)``: the damping ratio of one spring between two
  vertex masses (§5). Modal damping ratios are reported: ``zeta_1`` (lowest deformation
  mode; for a pinned object the lowest mode), ``zeta_b`` (breathing, Rayleigh quotient of
  uniform scaling), ``zeta_max`` (highest mode). The edge dashpot is stiffness-proportional
  (zeta grows with omega), so the slow shape modes are only lightly damped; raising ``c`` to
  damp them overdamps the fast ones and shrinks the explicit time step (below).
* Stability, for explicit Verlet / symplectic Euler:
    - ``dt_G = sqrt(2 m / (k n_max))``: Gershgorin bound for the springs alone (§4);
    - ``omega_max``: the largest eigenvalue of M^-1 K, where K is the Hessian of springs
      plus gas at the relaxed inflated state (pre-tension and gas included), found with
      ARPACK; ``dt_w = 2/omega_max * (sqrt(1 + zeta_max^2) - zeta_max)`` is the limit with
      the dashpot's (and drag's) explicit damping at that mode;
    - suggested ``dt``: ``min(0.5 dt_w, dt_G)`` rounded down to a value {1, 1.25, 2, 2.5,
      4, 5, 8} x 10^k that divides the 10 ms frame interval into a whole number of steps.
  Floor contact is not included: a penalty floor needs ``k_c <~ 0.25 m (2/dt)^2`` (§6).

Objects are written in their rest shape (uninflated): they inflate to ``s*`` during the
first tenths of a second while they fall.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from jaxplush.model.mesh import superellipsoid  # noqa: E402
from jaxplush.scene.write import write_scene  # noqa: E402

R_GAS = 8.314  # J/(mol K), as jaxplush.types.GAS_CONSTANT
TEMPERATURE = 293.15  # K, written into every scene explicitly
GRAVITY = (0.0, -9.81, 0.0)
FLOOR = 0.0
INFLATION = 1.05  # target free inflated size s* (linear)
ZETA_SPRING = 0.25  # per-spring damping ratio c / sqrt(2 k m)
DURATION = 2.0  # simulated seconds per scene
FRAME_DT = 0.01  # seconds between saved frames (~100 fps)
DT_SAFETY = 0.5  # suggested dt = DT_SAFETY x measured stability limit


# --------------------------------------------------------------------------- geometry


def icosphere(subdivisions: int, radius: float):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def rotation_to(a, b):
    """Rotation matrix taking unit vector a to unit vector b (Rodrigues)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-15:
        if c > 0:
            return np.eye(3)
        # 180 degrees about any axis perpendicular to a
        p = np.eye(3)[np.argmin(np.abs(a))]
        v = np.cross(a, p)
        v /= np.linalg.norm(v)
        return 2 * np.outer(v, v) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _far_sphere(d, c, r):
    """Largest t with |t d - c| = r for unit rays d (N,3) from the origin; -inf if missed."""
    b = d @ c
    disc = b * b - (c @ c - r * r)
    return np.where(disc >= 0, b + np.sqrt(np.maximum(disc, 0.0)), -np.inf)


def _far_capsule(d, a, b, r):
    """Largest t where the ray t d leaves the capsule (segment a-b, radius r); -inf if missed.

    The capsule is the union of the finite cylinder and its two end spheres; the farthest exit
    of a union is the largest of the parts' farthest exits.
    """
    t = np.maximum(_far_sphere(d, a, r), _far_sphere(d, b, r))
    axis = b - a
    length = float(np.linalg.norm(axis))
    u = axis / length
    dp = d - np.outer(d @ u, u)  # ray direction perpendicular to the axis
    ap = -a + (a @ u) * u  # (origin - a) perpendicular to the axis
    qa = np.einsum("ij,ij->i", dp, dp)
    qb = 2.0 * (dp @ ap)
    qc = ap @ ap - r * r
    disc = qb * qb - 4 * qa * qc
    hit = (disc >= 0) & (qa > 1e-14)
    s = np.where(hit, (-qb + np.sqrt(np.maximum(disc, 0.0))) / (2 * np.where(hit, qa, 1.0)), 0.0)
    along = (s[:, None] * d - a) @ u
    side = np.where(hit & (along >= 0) & (along <= length), s, -np.inf)
    return np.maximum(t, side)


# Bear lobes in design units (metres before the final rescale to BEAR_HEIGHT): capsules
# (a, b, radius). Every lobe contains the ray origin (0,0,0), so each lobe's radial function
# is continuous and so is their maximum: the star hull has no radial "walls".
BEAR_LOBES = {
    "body": ((0.0, -0.03, 0.0), (0.0, 0.02, 0.0), 0.075),
    "head": ((0.0, 0.0, 0.0), (0.0, 0.125, 0.01), 0.06),
    "snout": ((0.0, 0.0, 0.0), (0.0, 0.105, 0.055), 0.03),
    "ear_l": ((0.0, 0.0, 0.0), (-0.06, 0.18, 0.0), 0.025),
    "ear_r": ((0.0, 0.0, 0.0), (0.06, 0.18, 0.0), 0.025),
    "arm_l": ((0.0, 0.0, 0.0), (-0.13, -0.03, 0.03), 0.03),
    "arm_r": ((0.0, 0.0, 0.0), (0.13, -0.03, 0.03), 0.03),
    "leg_l": ((0.0, 0.0, 0.0), (-0.055, -0.125, 0.025), 0.036),
    "leg_r": ((0.0, 0.0, 0.0), (0.055, -0.125, 0.025), 0.036),
}
BEAR_HEIGHT = 0.30  # m, feet to ear tips
BEAR_SUBDIVISIONS = 4  # 2562 vertices: limbs need ~5 vertices across


def bear_radius(d):
    """Radial function of the union of BEAR_LOBES along unit rays d (N,3)."""
    r = np.full(len(d), -np.inf)
    for a, b, rho in BEAR_LOBES.values():
        r = np.maximum(r, _far_capsule(d, np.asarray(a, float), np.asarray(b, float), rho))
    assert np.all(np.isfinite(r)) and np.all(r > 0), "every ray must hit the body"
    return r


def bear_mesh(iterations: int = 300, step: float = 0.3):
    """Star hull of BEAR_LOBES on an icosphere, with ray directions relaxed on the sphere.

    The icosphere's unit directions d_i are moved toward the average of their neighbours
    weighted by the squared 3-D edge length (long 3-D edges pull their ends together), then
    re-projected onto the lobes. This moves vertices onto the limbs, where plain radial
    projection stretches the edges. A step that would invert a spherical triangle is
    refused; the directions with the smallest max/min edge ratio are kept. Topology is
    the icosphere's throughout, and since every spherical triangle stays positively
    oriented the surface r(d) d stays embedded, closed and outward-wound.

    Returns (vertices (N,3) in metres with the body centre at the origin, faces (F,3),
    edge-length ratio before relaxation, after).
    """
    v0, faces = icosphere(BEAR_SUBDIVISIONS, 1.0)
    d = v0 / np.linalg.norm(v0, axis=1, keepdims=True)
    edges = trimesh.Trimesh(v0, faces, process=False).edges_unique
    n = len(d)

    def place(dirs):
        p = bear_radius(dirs)[:, None] * dirs
        lengths = np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1)
        return p, lengths

    _, lengths = place(d)
    ratio0 = lengths.max() / lengths.min()
    best_ratio, best_d = ratio0, d.copy()
    for _ in range(iterations):
        _, lengths = place(d)
        w = lengths**2
        acc = np.zeros_like(d)
        wsum = np.zeros(n)
        np.add.at(acc, edges[:, 0], w[:, None] * d[edges[:, 1]])
        np.add.at(acc, edges[:, 1], w[:, None] * d[edges[:, 0]])
        np.add.at(wsum, edges[:, 0], w)
        np.add.at(wsum, edges[:, 1], w)
        new = d + step * (acc / wsum[:, None] - d)
        new /= np.linalg.norm(new, axis=1, keepdims=True)
        orient = np.einsum("ij,ij->i", new[faces[:, 0]], np.cross(new[faces[:, 1]], new[faces[:, 2]]))
        if np.any(orient <= 0):
            break
        d = new
        _, lengths = place(d)
        ratio = lengths.max() / lengths.min()
        if ratio < best_ratio:
            best_ratio, best_d = ratio, d.copy()
    p, _ = place(best_d)
    p *= BEAR_HEIGHT / np.ptp(p[:, 1])
    return p, faces, ratio0, best_ratio


# --------------------------------------------------------------------------- mechanics


def unique_edges(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def volume(x, faces):
    c = x - x.mean(axis=0)
    return float(np.einsum("ij,ij->", c[faces[:, 0]], np.cross(c[faces[:, 1]], c[faces[:, 2]])) / 6.0)


def volume_grad(x, faces):
    """dV/dx (N,3)."""
    a, b, c = (x[faces[:, i]] for i in range(3))
    g = np.zeros_like(x)
    np.add.at(g, faces[:, 0], np.cross(b, c) / 6.0)
    np.add.at(g, faces[:, 1], np.cross(c, a) / 6.0)
    np.add.at(g, faces[:, 2], np.cross(a, b) / 6.0)
    return g


def _skew(u):
    """(n,3,3) matrices [u]_x with [u]_x w = u x w."""
    z = np.zeros(len(u))
    return np.stack([np.stack([z, -u[:, 2], u[:, 1]], -1),
                     np.stack([u[:, 2], z, -u[:, 0]], -1),
                     np.stack([-u[:, 1], u[:, 0], z], -1)], axis=1)


def _block_matrix(rows, cols, blocks, n):
    """Sparse (3n,3n) matrix from (b,) block positions and (b,3,3) blocks (summed)."""
    r = (3 * rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    c = (3 * cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    return sp.coo_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(3 * n, 3 * n)).tocsr()


def edge_blocks(x, edges, rest, k, c):
    """Spring Hessian and dashpot matrix, both (3N,3N) sparse."""
    i, j = edges[:, 0], edges[:, 1]
    dvec = x[i] - x[j]
    length = np.linalg.norm(dvec, axis=1)
    dh = dvec / length[:, None]
    ddt = dh[:, :, None] * dh[:, None, :]
    eye = np.eye(3)[None]
    kb = k * (ddt + (1.0 - rest / length)[:, None, None] * (eye - ddt))
    cb = c * ddt
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([i, j, j, i])
    n = len(x)
    K = _block_matrix(rows, cols, np.concatenate([kb, kb, -kb, -kb]), n)
    C = _block_matrix(rows, cols, np.concatenate([cb, cb, -cb, -cb]), n)
    return K, C


def volume_hessian(x, faces):
    """d2V/dx2 (3N,3N) sparse. For face (a,b,c): d2V/dx_a dx_b = -[x_c]/6, d2V/dx_a dx_c = [x_b]/6."""
    rows, cols, blocks = [], [], []
    for p, q, r in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        a, b, c = faces[:, p], faces[:, q], faces[:, r]
        rows += [a, a]
        cols += [b, c]
        blocks += [-_skew(x[c]) / 6.0, _skew(x[b]) / 6.0]
    return _block_matrix(np.concatenate(rows), np.concatenate(cols), np.concatenate(blocks), len(x))


def relax(x0, faces, edges, rest, k, nrt, *, mass=0.0, gravity=(0.0, 0.0, 0.0), fixed=()):
    """Static equilibrium of springs + gas (+ gravity if pinned) by L-BFGS from x0."""
    n = len(x0)
    free = np.ones(n, bool)
    free[list(fixed)] = False
    g_vec = np.asarray(gravity, float)

    def unpack(z):
        x = x0.copy()
        x[free] = z.reshape(-1, 3)
        return x

    def fun(z):
        x = unpack(z)
        dvec = x[edges[:, 0]] - x[edges[:, 1]]
        length = np.linalg.norm(dvec, axis=1)
        stretch = length - rest
        vol = volume(x, faces)
        e = 0.5 * k * np.sum(stretch**2) - mass * np.sum(x @ g_vec)
        grad = np.zeros_like(x)
        t = (k * stretch / length)[:, None] * dvec
        np.add.at(grad, edges[:, 0], t)
        np.add.at(grad, edges[:, 1], -t)
        grad -= mass * g_vec[None]
        if nrt > 0:
            e -= nrt * math.log(vol)
            grad -= nrt / vol * volume_grad(x, faces)
        return e, grad[free].ravel()

    res = scipy.optimize.minimize(fun, x0[free].ravel(), jac=True, method="L-BFGS-B",
                                  options=dict(maxiter=20000, maxcor=30, gtol=1e-12, ftol=1e-15))
    x = unpack(res.x)
    gmax = float(np.abs(fun(res.x)[1]).max())
    return x, gmax


def rigid_modes(x):
    """(3N,6) orthonormal translations and infinitesimal rotations about the centroid."""
    c = x - x.mean(axis=0)
    cols = []
    for a in range(3):
        t = np.zeros_like(x)
        t[:, a] = 1.0
        cols.append(t.ravel())
    for a in range(3):
        w = np.zeros(3)
        w[a] = 1.0
        cols.append(np.cross(w, c).ravel())
    q, _ = np.linalg.qr(np.stack(cols, axis=1))
    return q


def modal_analysis(x, faces, edges, rest, k, c, nrt, mass_per_vertex, fixed=(), drag=0.0):
    """Frequencies and damping ratios at configuration x.

    K = spring Hessian + nRT (g g^T / V^2 - H_V / V) (gas, g = dV/dx, H_V = d2V/dx2), mass
    m I. Pinned vertices are removed; for a free object the six rigid modes are lifted out
    of the way (K + alpha R R^T). Damping: the dashpot matrix C plus air drag (C + drag m I,
    adding drag/(2 omega) to every zeta). Returns dict with omega_max, zeta_max, omega_1,
    zeta_1, omega_b, zeta_b.
    """
    n = len(x)
    Ks, C = edge_blocks(x, edges, rest, k, c)
    u_cols, w_diag = [], []
    if nrt > 0:
        vol = volume(x, faces)
        Ks = Ks - (nrt / vol) * volume_hessian(x, faces)
        u_cols.append(volume_grad(x, faces).ravel())
        w_diag.append(nrt / vol**2)
    keep = np.ones(3 * n, bool)
    for f in fixed:
        keep[3 * f:3 * f + 3] = False
    Ks = Ks[keep][:, keep].tocsc()
    Cr = C[keep][:, keep]
    dim = int(keep.sum())
    U = np.stack(u_cols, axis=1)[keep] if u_cols else np.zeros((dim, 0))
    W = np.asarray(w_diag)

    def kmul(v):
        return Ks @ v + U @ (W * (U.T @ v))

    Kop = spla.LinearOperator((dim, dim), matvec=kmul, dtype=np.float64)
    start = np.random.default_rng(0).standard_normal(dim)  # fixed ARPACK start: reproducible files
    lam_max, vec_max = spla.eigsh(Kop, k=1, which="LA", tol=1e-8, v0=start)
    lam_max = float(lam_max[0])
    vec_max = vec_max[:, 0]

    # Lowest modes by shift-invert. For a free object the six rigid modes are lifted to
    # 2 lam_max (K + alpha R R^T, exact at equilibrium where R spans K's null space) so the
    # lowest eigenvalues found are deformations. (Ks + U W U^T - sigma I)^-1 by Woodbury.
    if len(fixed) == 0:
        U = np.concatenate([U, rigid_modes(x)], axis=1)
        W = np.concatenate([W, np.full(6, 2.0 * lam_max)])
    sigma = -1e-4 * lam_max
    lu = spla.splu((Ks - sigma * sp.identity(dim, format="csc")).tocsc())
    AiU = lu.solve(U) if U.shape[1] else U
    small = np.diag(1.0 / W) + U.T @ AiU if U.shape[1] else None

    def opinv(v):
        y = lu.solve(v)
        if small is None:
            return y
        return y - AiU @ np.linalg.solve(small, U.T @ y)

    OPinv = spla.LinearOperator((dim, dim), matvec=opinv, dtype=np.float64)
    lam, vecs = spla.eigsh(Kop, k=8, sigma=sigma, which="LM", OPinv=OPinv, tol=1e-10, v0=start)
    order = np.argsort(lam)
    lam, vecs = lam[order], vecs[:, order]
    if lam[0] < -1e-8 * lam_max:
        raise RuntimeError(f"unstable configuration: lowest stiffness eigenvalue {lam[0]:.3g}")
    # Skip true zero modes left by pins (e.g. spinning about the vertical through a single pin).
    nonzero = lam > 1e-8 * lam_max
    lam, vecs = lam[nonzero], vecs[:, nonzero]
    m = mass_per_vertex

    def zeta(vec, lam_):
        vec = vec / np.linalg.norm(vec)
        omega = math.sqrt(lam_ / m)
        return float(vec @ (Cr @ vec)) / (2.0 * m * omega) + drag / (2.0 * omega)

    # Breathing: Rayleigh quotient of uniform scaling about the centroid (free DOFs only).
    ub = (x - x.mean(axis=0)).ravel()[keep]
    lam_b = float(ub @ kmul(ub)) / float(ub @ ub)
    return dict(
        omega_max=math.sqrt(lam_max / m), zeta_max=zeta(vec_max, lam_max),
        omega_1=math.sqrt(lam[0] / m), zeta_1=zeta(vecs[:, 0], lam[0]),
        omega_b=math.sqrt(lam_b / m), zeta_b=zeta(ub, lam_b),
    )


def nice_dt(limit, frame_dt=None):
    """Largest m x 10^k (m in 1, 1.25, 2, 2.5, 4, 5, 8) not above ``limit``.

    With ``frame_dt`` only values that divide it into a whole number of steps qualify.
    """
    e = math.floor(math.log10(limit))
    for exp in range(e, e - 4, -1):
        for mant in (8.0, 5.0, 4.0, 2.5, 2.0, 1.25, 1.0):
            dt = float(f"{mant}e{exp}")
            if dt > limit * (1 + 1e-12):
                continue
            if frame_dt is None or abs(frame_dt / dt - round(frame_dt / dt)) < 1e-9:
                return dt
    raise ValueError(f"no round time step below {limit}")


# --------------------------------------------------------------------------- objects


def make_object(name, vertices, faces, *, total_weight, k, zeta_spring=ZETA_SPRING,
                inflation=INFLATION, translate=(0.0, 0.0, 0.0), fixed=None, drag=None,
                calibrate=False, scale=None):
    """Object dict for the writer, with nmol and dashpot derived, plus its analysis.

    ``vertices`` are written as given; with ``scale`` the file says ``scale S`` and every
    number here (rest lengths, volume, nmol) is computed on the scaled mesh, as the parser
    builds it. ``translate`` does not change any of them. ``calibrate``: solve for nmol
    numerically (see below) instead of using the sphere formula. Pinned objects are analysed
    hanging from their pins under GRAVITY; free ones at their free inflated equilibrium.
    """
    written = np.asarray(vertices, np.float64)
    vertices = written * (1.0 if scale is None else float(scale))
    faces = np.asarray(faces, np.int64)
    edges = unique_edges(faces)
    rest = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    m = total_weight / n
    sum_l2 = float(np.sum(rest**2))
    s = inflation
    rt = R_GAS * TEMPERATURE
    nmol_formula = k * sum_l2 * s * (s - 1.0) / (3.0 * rt)  # docs/model.md §8 item 5
    dashpot = zeta_spring * math.sqrt(2.0 * k * m)
    valence = np.bincount(edges.ravel(), minlength=n)
    v0 = volume(vertices, faces)
    centred = vertices - vertices.mean(axis=0)

    def free_size(nmol_):
        """(V*/V0)^(1/3) of the free object (no gravity, no pins) at its equilibrium."""
        x_, g_ = relax(vertices.mean(axis=0) + s * centred, faces, edges, rest, k, nmol_ * rt)
        return (volume(x_, faces) / v0) ** (1.0 / 3.0), x_, g_

    nmol = nmol_formula
    s_free, x_eq, gmax = free_size(nmol)
    if calibrate:
        # The formula assumes uniform scaling is the equilibrium (exact for spheres only). A
        # lobed body gains volume by unfolding its creases, so solve s_free(nmol) = s by a
        # secant on log(s_free - 1) against log(nmol).
        pts = [(math.log(nmol), math.log(s_free - 1.0))]
        nmol = nmol * (s - 1.0) / (s_free - 1.0)
        for _ in range(20):
            s_free, x_eq, gmax = free_size(nmol)
            if abs(s_free - s) < 1e-4:
                break
            pts.append((math.log(nmol), math.log(s_free - 1.0)))
            (a0, b0), (a1, b1) = pts[-2], pts[-1]
            slope = (b1 - b0) / (a1 - a0) if a1 != a0 else 1.0
            nmol = math.exp(a1 + (math.log(s - 1.0) - b1) / slope)
        else:
            raise RuntimeError(f"{name}: nmol calibration did not converge (s = {s_free:.5f})")
    nrt = nmol * rt

    fixed = list(fixed or [])
    if fixed:
        # hanging under gravity from its pins: start from the uniformly inflated shape
        # scaled about the (first) pin, so the pins stay put
        pin = vertices[fixed[0]]
        start = pin + s * (vertices - pin)
        x_eq, gmax = relax(start, faces, edges, rest, k, nrt, mass=m, gravity=GRAVITY, fixed=fixed)
    if not gmax < 1e-5 * k * rest.mean():
        raise RuntimeError(f"{name}: static relaxation did not converge (max force {gmax:.3g} N)")
    v_eq = volume(x_eq, faces)
    strain = np.linalg.norm(x_eq[edges[:, 0]] - x_eq[edges[:, 1]], axis=1) / rest - 1.0
    modes = modal_analysis(x_eq, faces, edges, rest, k, dashpot, nrt, m, fixed=fixed, drag=drag or 0.0)

    dt_g = math.sqrt(2.0 * m / (k * valence.max()))
    z = modes["zeta_max"]
    dt_w = 2.0 / modes["omega_max"] * (math.sqrt(1.0 + z * z) - z)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    info = dict(
        name=name, n_vertices=n, n_edges=len(edges), n_faces=len(faces), mass=total_weight,
        m=m, k=k, dashpot=dashpot, drag=drag, nmol=nmol, nmol_formula=nmol_formula,
        calibrated=calibrate, sum_l2=sum_l2, v0=v0, p_rest=nrt / v0, p_inflated=nrt / v_eq,
        s_nominal=s, s_free=s_free, s_measured=(v_eq / v0) ** (1 / 3), relax_residual=gmax,
        strain_min=float(strain.min()), strain_mean=float(strain.mean()), strain_max=float(strain.max()),
        pinned=bool(fixed), n_max=int(valence.max()), dt_g=dt_g, dt_w=dt_w,
        edge_ratio=float(rest.max() / rest.min()),
        min_angle_deg=float(np.degrees(mesh.face_angles.min())), **modes,
    )
    obj = dict(name=name, vertices=written, faces=faces, total_weight=total_weight,
               k_structural=k, dashpot=dashpot, drag=drag, nmol=nmol, scale=scale,
               translate=[float(t) for t in translate], fixed=fixed or None)
    return obj, info


def check_mesh(name, vertices, faces):
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    area = mesh.area_faces
    problems = []
    if not mesh.is_watertight:
        problems.append("not watertight")
    if not mesh.is_winding_consistent:
        problems.append("winding inconsistent")
    if not mesh.volume > 0:
        problems.append(f"volume {mesh.volume:.3g} <= 0")
    if area.min() <= 1e-12 * mesh.scale**2:
        problems.append("degenerate face")
    if len(mesh.split(only_watertight=False)) != 1:
        problems.append("several components")
    if problems:
        raise RuntimeError(f"{name}: " + ", ".join(problems))


# --------------------------------------------------------------------------- scenes


def ball_mesh(subdivisions=3, radius=0.1):
    return icosphere(subdivisions, radius)


def scene_ball_drop():
    v, f = ball_mesh(3, 0.1)
    drop = 0.4  # m, lowest point above the floor
    obj, info = make_object("ball", v, f, total_weight=0.1, k=500.0,
                            translate=(0.0, FLOOR + drop - v[:, 1].min(), 0.0))
    text = ("A 642-vertex inflated ball (icosphere, radius 0.1 m, 0.1 kg) dropped with its "
            f"lowest point {drop} m above the floor.")
    return "ball_drop.obj", text, [obj], [info], dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE)


_BEAR_CACHE = {}


def bear_object(translate_xz=(0.0, 0.0), drop=0.15):
    """The bear object (analysis cached: two scenes use it) with its feet ``drop`` above the floor."""
    if "bear" not in _BEAR_CACHE:
        v, f, r0, _ = bear_mesh()
        obj, info = make_object("bear", v, f, total_weight=0.3, k=500.0, calibrate=True)
        info["edge_ratio_unrelaxed"] = r0
        _BEAR_CACHE["bear"] = (obj, info)
    obj, info = _BEAR_CACHE["bear"]
    lift = FLOOR + drop - obj["vertices"][:, 1].min()
    return dict(obj, translate=[float(translate_xz[0]), float(lift), float(translate_xz[1])]), dict(info)


def scene_bear():
    drop = 0.15
    obj, info = bear_object(drop=drop)
    text = ("A 2562-vertex plush bear (one closed surface: body, head, snout, two ears, two "
            f"arms, two legs), {BEAR_HEIGHT} m tall, 0.3 kg, dropped upright with its feet "
            f"{drop} m above the floor. It faces +z; y is up.")
    return "bear.obj", text, [obj], [info], dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE)


def scene_hanging():
    radius = 0.1
    v, f = ball_mesh(2, 1.0)  # written as a unit sphere with "scale 0.1" (exercises scale)
    # turn the icosphere so that one of its (valence-5) vertices points straight up
    top = int(np.argmax(v[:, 1]))
    v = v @ rotation_to(v[top], np.array([0.0, 1.0, 0.0])).T
    top = int(np.argmax(v[:, 1]))
    pin_height = 1.0
    obj, info = make_object("hanging_ball", v, f, total_weight=0.1, k=50.0, scale=radius,
                            drag=1.0, translate=(0.0, pin_height - radius * v[top, 1], 0.0),
                            fixed=[top])
    text = ("A soft 162-vertex inflated ball (icosphere, radius 0.1 m, 0.1 kg, k = 50 N/m) "
            f"hanging from one pinned vertex at its top (at y = {pin_height:g} m); gravity on, no "
            "floor. It starts undeformed, drops, stretches and bounces on its pin. Written as a "
            "unit sphere with 'scale 0.1'. A light air drag (1/s) slowly damps the bounce and any "
            "swing, which the edge dashpot cannot damp (a rigid swing stretches no edge). The "
            "modal numbers are for the pinned ball at its hanging equilibrium (gravity included); "
            "its lowest mode is the pendulum swing.")
    return "hanging.obj", text, [obj], [info], dict(gravity=GRAVITY, temperature=TEMPERATURE)


def scene_two_plushies():
    vb, fb = ball_mesh(3, 0.08)
    ball, binfo = make_object("stiff_ball", vb, fb, total_weight=0.08, k=1000.0,
                              translate=(0.30, FLOOR + 0.30 - vb[:, 1].min(), 0.0))
    bear, info = bear_object(translate_xz=(-0.25, 0.0), drop=0.15)
    text = ("Two objects falling onto the floor side by side, 0.55 m apart along x (there is "
            "no object-object contact yet, so they are kept well apart): the bear of "
            "bear.obj (feet 0.15 m up, at x = -0.25) and a stiffer, smaller ball "
            "(radius 0.08 m, 0.08 kg, k = 1000 N/m; lowest point 0.30 m up, at x = +0.30).")
    return ("two_plushies.obj", text, [bear, ball], [info, binfo],
            dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE))


PILE_FRICTION = 0.6  # Coulomb coefficient of the pile scene, on the floor and between the cushions
# Contact candidates per object pair: a cushion lying on another has up to about 430 of its 642
# vertices in the other's (margin-inflated) bounding box (measured); let every vertex take part.
PILE_CAPACITY = 642
# The pile: three cushions, bottom to top (half-width a, half-thickness c, mass), stacked centred.
PILE_CUSHIONS = (("bottom", 0.12, 0.05, 0.1), ("middle", 0.09, 0.04, 0.1), ("top", 0.065, 0.03, 0.1))
PILE_EXPONENT = 4  # superellipsoid exponent: flat faces, rounded rims
PILE_GAP = 0.02  # m between a cushion's rest-shape top and the next one's bottom
PILE_DRAG = 5.0  # 1/s, air drag of every cushion (see scene_plush_pile)


def scene_plush_pile():
    # Why a stack of flat cushions and not a pyramid of balls (measured, see docs/contact.md): two balls
    # under a third roll apart, since rolling needs no slip at the floor and only friction between
    # the plushies could stop them, and that friction, explicit and velocity level, creeps (about
    # 1.6 cm/s per ball). A ball on a cushion, or in the groove between two, rolls off (a ball on a
    # convex top, and along the groove, is unstable). Flat cushions need no friction to stay
    # stacked: a flat top gives no push sideways. An air drag (PILE_DRAG) damps what the edge
    # dashpot barely damps: the slow bounce of the whole stack on its gas springs, started by the
    # inflation from the rest shapes (the dashpot is stiffness-proportional; zeta_1 ~ 0.02).
    # Measured at 2 s, largest vertex speed: 0.6 m/s without drag, 0.12 m/s with 2/s, 2-3 mm/s with
    # 5/s. Ellipsoid cushions (convex tops) drift sideways off each other; flat tops do not.
    objs, infos = [], []
    y = FLOOR + 0.002
    for name, a, c, mass in PILE_CUSHIONS:
        v, f = superellipsoid(a, c, PILE_EXPONENT)
        # nmol calibrated: the sphere formula assumes uniform scaling and overinflates a flat body
        obj, info = make_object(name, v, f, total_weight=mass, k=800.0, calibrate=True, drag=PILE_DRAG,
                                translate=(0.0, y + c, 0.0))
        objs.append(obj)
        infos.append(info)
        y += 2 * c + PILE_GAP
    sizes = ", ".join(f"{name} {2 * a * 100:g} x {2 * c * 100:g} x {2 * a * 100:g} cm"
                      for name, a, c, _ in PILE_CUSHIONS)
    text = (f"Three plushies piled up: three flat cushions ({sizes}; 0.1 kg and k = 800 N/m each; "
            f"superellipsoids |x/a|^{PILE_EXPONENT} + |y/c|^{PILE_EXPONENT} + |z/a|^{PILE_EXPONENT} = 1 "
            f"on a 642-vertex icosphere) stacked centred on the floor, each {PILE_GAP * 100:g} cm above "
            "the one below (rest shapes); they inflate, settle on each other and come to rest. Soft-soft "
            f"contact (on by default for several objects) holds them up; Coulomb friction {PILE_FRICTION:g} on "
            f"the floor and between the cushions. An air drag of {PILE_DRAG:g}/s damps the slow bounce of the "
            "stack on its gas springs, which the edge dashpot barely damps. Flat cushions rather than "
            "balls: two balls roll apart under a third (friction between plushies is explicit and "
            "creeps, see README), and a ball rolls off a cushion's top or out of the groove between two.")
    return ("plush_pile.obj", text, objs, infos,
            dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE, floor_friction=PILE_FRICTION,
                 contact_capacity=PILE_CAPACITY, contact_friction=PILE_FRICTION))


def write_path_csv(fname, times, positions):
    """Write a driven vertices' path file (docs/formats.md §2.7): a header, then one row
    t,x1,y1,z1,... per sample; ``positions`` (S, D, 3). Floats with repr (deterministic)."""
    positions = np.asarray(positions, np.float64)
    head = "t," + ",".join(f"x{j + 1},y{j + 1},z{j + 1}" for j in range(positions.shape[1]))
    rows = [",".join(repr(float(v)) for v in [t, *p.ravel().tolist()]) for t, p in zip(times, positions)]
    (HERE / fname).write_text("\n".join([head, *rows]) + "\n")


def scene_lifted():
    v, f = ball_mesh(2, 0.1)
    lift = FLOOR - v[:, 1].min()
    top = int(np.argmax(v[:, 1]))
    obj, info = make_object("lifted_ball", v, f, total_weight=0.1, k=200.0, translate=(0.0, lift, 0.0))
    start = v[top] + np.array([0.0, lift, 0.0])
    times = [0.0, 0.5, 0.8]
    positions = [[start], [start + [0.0, 0.3, 0.0]], [start + [0.0, 0.3, 0.0]]]
    write_path_csv("lifted_path.csv", times, positions)
    release = 0.8
    obj["driven"] = [dict(path="lifted_path.csv", vertices=[top], until=release)]
    text = ("A 162-vertex inflated ball (icosphere, radius 0.1 m, 0.1 kg, k = 200 N/m) resting on the "
            "floor is lifted by its top vertex, driven along lifted_path.csv: up 0.3 m in 0.5 s, held "
            f"for 0.3 s, then released ('until {release:g}'): from then on the vertex is free and the "
            "ball drops back onto the floor. The modal numbers are for the free ball.")
    return "lifted.obj", text, [obj], [info], dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE)


def scene_squeezed():
    radius = 0.1
    v, f = ball_mesh(2, radius)
    lift = FLOOR - v[:, 1].min()
    obj, info = make_object("squeezed_ball", v, f, total_weight=0.1, k=200.0, translate=(0.0, lift, 0.0))
    times = np.array([0.0, 0.5, 0.8, 1.3])
    depth = np.array([0.0, 0.04, 0.04, 0.0])       # how far each patch has moved in, m
    entries = []
    for side, fname in ((1.0, "squeezed_right.csv"), (-1.0, "squeezed_left.csv")):
        patch = np.flatnonzero(side * v[:, 0] > 0.8 * radius)
        x = v[patch] + np.array([0.0, lift, 0.0])
        positions = [x - side * d * np.array([1.0, 0.0, 0.0]) for d in depth]
        write_path_csv(fname, times, positions)
        entries.append(dict(path=fname, vertices=patch.tolist()))
    obj["driven"] = entries
    n = sum(len(e["vertices"]) for e in entries)
    text = ("A 162-vertex inflated ball (icosphere, radius 0.1 m, 0.1 kg, k = 200 N/m) on the floor, "
            f"squeezed between two driven patches ({n} vertices: the caps beyond x = +-0.08 m): each "
            "moves 4 cm inwards in 0.5 s (squeezed_right.csv, squeezed_left.csv), holds for 0.3 s, "
            "moves back in 0.5 s and then holds. The modal numbers are for the free ball.")
    return "squeezed.obj", text, [obj], [info], dict(gravity=GRAVITY, floor=FLOOR, temperature=TEMPERATURE)


SCENES = (scene_ball_drop, scene_bear, scene_hanging, scene_two_plushies, scene_plush_pile, scene_lifted,
          scene_squeezed)


# --------------------------------------------------------------------------- output


def run_plan(infos):
    dt = nice_dt(min(min(DT_SAFETY * i["dt_w"], i["dt_g"]) for i in infos), FRAME_DT)
    steps = int(math.ceil(DURATION / dt - 1e-9))
    save_every = max(1, int(round(FRAME_DT / dt)))
    steps = int(math.ceil(steps / save_every)) * save_every
    return dt, steps, save_every


def info_lines(i):
    if i["calibrated"]:
        gas_how = (f"chosen so the free equilibrium has (V*/V0)^(1/3) = {i['s_nominal']:g} "
                   f"(the sphere formula of docs/model.md §8.5 would give {i['nmol_formula']:.4g})")
    else:
        gas_how = f"from docs/model.md §8.5 for s* = {i['s_nominal']:g}"
    inflated = f"free inflated equilibrium: (V*/V0)^(1/3) = {i['s_free']:.4f}"
    if i["pinned"]:
        inflated += f"; hanging equilibrium: (V/V0)^(1/3) = {i['s_measured']:.4f}"
    eq = "hanging" if i["pinned"] else "free inflated"
    first = "lowest mode" if i["pinned"] else "lowest deformation mode"
    return [
        f"object {i['name']}: {i['n_vertices']} vertices, {i['n_edges']} edges, {i['n_faces']} faces; "
        f"mass {i['mass']:g} kg (m = {i['m']:.4g} kg/vertex); max valence {i['n_max']}",
        f"  k_structural {i['k']:g} N/m; dashpot {i['dashpot']:.4g} N s/m (zeta per spring "
        f"c/sqrt(2km) = {ZETA_SPRING:g})" + (f"; drag {i['drag']:g} 1/s" if i.get("drag") else ""),
        f"  gas: nmol {i['nmol']:.4g} mol, {gas_how}",
        f"  T = {TEMPERATURE} K, sum L^2 = {i['sum_l2']:.4g} m^2, rest volume {i['v0']:.4g} m^3; "
        f"pressure {i['p_rest']:.4g} Pa at rest, {i['p_inflated']:.4g} Pa {eq}",
        f"  {inflated}; edge strain there {i['strain_min']:+.3f} .. {i['strain_max']:+.3f} "
        f"(mean {i['strain_mean']:+.3f})",
        f"  modes at the {eq} equilibrium: {first} {i['omega_1']:.4g} rad/s (zeta {i['zeta_1']:.3f}), "
        f"breathing ~{i['omega_b']:.4g} rad/s (zeta {i['zeta_b']:.3f}), "
        f"highest {i['omega_max']:.4g} rad/s (zeta {i['zeta_max']:.3f})",
        f"  stability: Gershgorin dt_G = sqrt(2m/(k n_max)) = {i['dt_g']:.3g} s; measured "
        f"2/omega_max = {2 / i['omega_max']:.3g} s, with the damping dt_w = {i['dt_w']:.3g} s",
        f"  edge length max/min {i['edge_ratio']:.3g}"
        + (f" (plain radial projection: {i['edge_ratio_unrelaxed']:.3g})" if "edge_ratio_unrelaxed" in i else "")
        + f"; smallest face angle {i['min_angle_deg']:.1f} deg",
    ]


def header_text(fname, description, infos, dt, steps, save_every):
    stem = Path(fname).stem
    lines = [
        f"jaxplush scene {fname}: generated by scenes/make_scenes.py; edit that script, not this file.",
        "",
        *_wrap(description),
        "",
        f"run: jaxplush simulate scenes/{fname} --steps {steps} --dt {dt:g} --save-every {save_every} --out {stem}.h5",
        f"     ({steps * dt:g} s simulated, {steps // save_every} frames at {save_every * dt * 1e3:g} ms)",
        f"dt = {DT_SAFETY:g} x the smallest stability limit below, rounded down; "
        "a stiff penalty floor may need a smaller one.",
        "",
    ]
    for i in infos:
        lines += info_lines(i)
    return "\n".join(lines)


def _wrap(text, width=92):
    words, out, cur = text.split(), [], ""
    for w in words:
        if cur and len(cur) + 1 + len(w) > width:
            out.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}" if cur else w
    if cur:
        out.append(cur)
    return out


def print_table(rows):
    cols = [("scene", "{}"), ("object", "{}"), ("V", "{}"), ("E", "{}"), ("F", "{}"),
            ("mass", "{:g}"), ("k", "{:g}"), ("dashpot", "{:.3g}"), ("nmol", "{:.3g}"),
            ("P_rest", "{:.4g}"), ("s*", "{:.4f}"), ("zeta_1", "{:.3f}"), ("zeta_max", "{:.3f}"),
            ("L_max/L_min", "{:.2f}"), ("dt_G", "{:.3g}"), ("dt_w", "{:.3g}"), ("dt", "{:.3g}"),
            ("steps", "{}")]
    keys = ["scene", "name", "n_vertices", "n_edges", "n_faces", "mass", "k", "dashpot", "nmol",
            "p_rest", "s_free", "zeta_1", "zeta_max", "edge_ratio", "dt_g", "dt_w", "dt", "steps"]
    table = [[fmt.format(r[k]) for (_, fmt), k in zip(cols, keys)] for r in rows]
    widths = [max(len(h), *(len(t[c]) for t in table)) for c, (h, _) in enumerate(cols)]
    print("  ".join(h.rjust(w) for (h, _), w in zip(cols, widths)))
    for t in table:
        print("  ".join(s.rjust(w) for s, w in zip(t, widths)))


# --------------------------------------------------------------------------- verification


def read_objects(path):
    """Independent minimal reader: (name, vertices (scaled+translated), 0-based local faces)."""
    verts, objs, cur = [], [], None
    for raw in Path(path).read_text().splitlines():
        tok = raw.split("#", 1)[0].split()
        if not tok:
            continue
        if cur is None:
            cur = dict(name=None, faces=[], scale=1.0, translate=np.zeros(3), first=len(verts))
        if tok[0] == "v":
            verts.append([float(t) for t in tok[1:4]])
        elif tok[0] == "f":
            cur["faces"].append([int(t) - 1 for t in tok[1:4]])
        elif tok[0] == "o":
            cur["name"] = tok[1]
        elif tok[0] == "scale":
            cur["scale"] = float(tok[1])
        elif tok[0] == "translate":
            cur["translate"] = np.array([float(t) for t in tok[1:4]])
        elif tok[0] == "END_OBJECT":
            objs.append(cur)
            cur = None
    verts = np.asarray(verts)
    out = []
    for o in objs:
        faces = np.asarray(o["faces"])
        used = np.unique(faces)
        x = verts[used] * o["scale"] + o["translate"]
        out.append((o["name"], x, np.searchsorted(used, faces)))
    return out


def verify(path):
    for name, x, faces in read_objects(path):
        check_mesh(f"{path.name}:{name}", x, faces)
    try:
        import jaxplush.scene.parse as scene_mod
    except Exception as e:  # the parser may not exist (yet) in this checkout
        return f"trimesh ok; jaxplush.scene.parse not importable ({type(e).__name__}: {e})"
    scene = scene_mod.load_scene(path)
    return f"trimesh ok; load_scene ok ({scene.n_objects} object(s), {scene.n_vertices} vertices)"


def main():
    rows = []
    written = []
    for build in SCENES:
        fname, description, objects, infos, scene_kw = build()
        for o in objects:
            check_mesh(f"{fname}:{o['name']}", o["vertices"], o["faces"])
        dt, steps, save_every = run_plan(infos)
        header = header_text(fname, description, infos, dt, steps, save_every)
        path = HERE / fname
        write_scene(path, objects, header=header, **scene_kw)
        written.append(path)
        print(f"wrote {path.relative_to(ROOT)}")
        for line in header.splitlines()[2:]:
            print("  " + line)
        for i in infos:
            rows.append(dict(i, scene=fname, dt=dt, steps=steps))
    print()
    print_table(rows)
    print()
    for path in written:
        print(f"check {path.name}: {verify(path)}")


if __name__ == "__main__":
    main()
