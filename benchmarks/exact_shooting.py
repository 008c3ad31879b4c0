"""Prototype of exact multiple shooting (issue 53 item 2), float64, on a small ball dropped on a floor
with frames far apart: not yet part of the fit.

Each segment of SEG frames restarts from the observed positions at its node frame; the node's
velocity is an unknown, solved by Gauss-Newton on the segment's exact forward-mode Jacobian
(jax.jacfwd through jaxplush.rollout); the parameters are fitted by variable projection, their
Jacobian the exact reduced one, (I - J_v J_v^+) J_theta, with a Levenberg-Marquardt step held
within 0.3 in log space. It prints the residual RMS at the truth with solved node velocities
and with the central differences of the frames (what the fit's multiple shooting starts from),
then a fit from START (factors on k, dashpot, nmol).

    python benchmarks/exact_shooting.py                       # 42 vertices, 24 frames 40 steps apart
    START=1.5,0.6,1.4 ITERS=20 python benchmarks/exact_shooting.py
"""
import os, sys, time
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
from conftest import icosphere_text
import jaxplush

SUB = int(os.environ.get("SUB", 1))
S = int(os.environ.get("GAP", 40))           # steps between frames
T = int(os.environ.get("FRAMES", 24))        # frames after the start
M = int(os.environ.get("SEG", 2))            # frames per segment
DT = 2.5e-4
text = icosphere_text(subdivisions=SUB, radius=0.1, k=200.0, mass=0.05, nmol=1e-3, dashpot=0.05, floor=0.0,
                      translate=(0, 0.2, 0))
scene = jaxplush.parse_scene(text, "<proto>")
sim = jaxplush.make_simulator(scene, DT)
p_true = sim.params()
NAMES = ("k_structural", "dashpot", "nmol")
th_true = jnp.log(jnp.array([p_true.k_structural[0], p_true.dashpot[0], p_true.nmol[0]]))


def params(th):
    e = jnp.exp(th)
    return p_true._replace(k_structural=e[0:1], dashpot=e[1:2], nmol=e[2:3])


def frames_from(th, x, v, n):
    p = params(th)
    _, fr, _ = jaxplush.rollout(sim, p, sim.init_fn(p, x, v), n, S)
    return fr


# truth
x_start = jnp.asarray(sim.topology.x0)
obs = jnp.concatenate([x_start[None], frames_from(th_true, x_start, jnp.zeros_like(x_start), T)])   # (T+1, V, 3)
print("vertices", x_start.shape[0], "frames", T, "every", S, "steps", "lowest y", float(obs[..., 1].min()))
nodes = list(range(0, T, M))
H = S * DT


def _seg(th, v, x0, y):
    return (frames_from(th, x0, v, M) - y).ravel()


_res = jax.jit(_seg)
_jv = jax.jit(jax.jacfwd(_seg, argnums=1))
_jt = jax.jit(jax.jacfwd(_seg, argnums=0))


def _xy(k):
    return (obs[k] if k > 0 else x_start), obs[k + 1:k + 1 + M]


def seg_res(th, v, k):
    return _res(th, v, *_xy(k))


def v_init(k):
    if k == 0:
        return jnp.zeros_like(x_start)
    return (obs[k + 1] - obs[k - 1]) / (2 * H)


def res_j(th, v, k):
    return _res(th, v, *_xy(k))


def jac_v(th, v, k):
    return _jv(th, v, *_xy(k))


def jac_t(th, v, k):
    return _jt(th, v, *_xy(k))


def solve_v(th, vs, iters=8):
    """Gauss-Newton (LM-damped) on each node's velocity (node 0's is known: the start's)."""
    out = []
    for k, v in zip(nodes, vs):
        if k == 0:
            out.append(v)
            continue
        for _ in range(iters):
            r = res_j(th, v, k)
            J = jac_v(th, v, k).reshape(r.size, -1)
            if not (np.isfinite(np.asarray(r)).all() and np.isfinite(np.asarray(J)).all()):
                break
            step = -np.linalg.lstsq(np.asarray(J), np.asarray(r), rcond=1e-10)[0]
            v2 = v + step.reshape(v.shape)
            if float(jnp.sum(res_j(th, v2, k) ** 2)) < float(jnp.sum(r ** 2)):
                v = v2
            else:
                break
        out.append(v)
    return out


def reduced(th, vs):
    rs, Js = [], []
    for k, v in zip(nodes, vs):
        r = np.asarray(res_j(th, v, k))
        Jt = np.asarray(jac_t(th, v, k)).reshape(r.size, -1)
        if not (np.isfinite(r).all() and np.isfinite(Jt).all()):
            return np.full(1, np.nan), None
        if k > 0:
            Jv = np.asarray(jac_v(th, v, k)).reshape(r.size, -1)
            # the component of J_theta the node velocity cannot absorb
            Jt = Jt - Jv @ np.linalg.lstsq(Jv, Jt, rcond=1e-10)[0]
        rs.append(r), Js.append(Jt)
    return np.concatenate(rs), np.concatenate(Js)


t0 = time.time()
vs = solve_v(th_true, [v_init(k) for k in nodes])
r, _ = reduced(th_true, vs)
print(f"floor at the truth with solved node velocities: rms {np.sqrt(np.mean(r**2)):.3g} m ({time.time()-t0:.1f} s)")
r0 = np.concatenate([np.asarray(res_j(th_true, v_init(k), k)) for k in nodes])
print(f"... with central-difference velocities: rms {np.sqrt(np.mean(r0**2)):.3g} m")

for start in [np.array([float(x) for x in os.environ.get("START", "1.1,0.9,1.1").split(",")])]:
    th = th_true + jnp.log(jnp.asarray(start))
    vs = [v_init(k) for k in nodes]
    mu = 1e-3
    t0 = time.time()
    for it in range(int(os.environ.get("ITERS", 12))):
        vs = solve_v(th, vs)
        r, J = reduced(th, vs)
        loss = float(r @ r)
        g = J.T @ r
        A = J.T @ J
        while True:
            step = -np.linalg.solve(A + mu * np.diag(np.diag(A)), g)
            step = step * min(1.0, 0.3 / max(np.max(np.abs(step)), 1e-300))      # trust region 0.3 (log)
            th2 = th + step
            vs2 = solve_v(th2, vs)
            r2, _ = reduced(th2, vs2)
            if np.isfinite(r2).all() and float(r2 @ r2) < loss:
                th, vs, mu = th2, vs2, mu / 3
                break
            mu *= 4
            if mu > 1e6:
                break
        err = np.exp(np.asarray(th - th_true)) - 1
        print(f"  it {it}: loss {loss:.3g} errors {np.round(100 * err, 5)}% ({time.time()-t0:.0f} s)")
        if np.max(np.abs(step)) < 1e-9 or mu > 1e6:
            break
    print("start", start, "final errors %", np.round(100 * (np.exp(np.asarray(th - th_true)) - 1), 6))
