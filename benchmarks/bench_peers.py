"""jaxplush's forward step against a peer implementation of the same model in Taichi (and numpy).

The model is the ball-drop plush of benchmarks/bench_step.py (``ball_scene``: icosphere, k = 500 N/m,
0.1 kg, nmol 5e-4, floor 0, translate 0 0.3 0), written three more times, term by term as jaxplush
computes it (docs/model.md §1, §5, §6):

* springs on every unique edge, f_i += k (1 - L/l) (x_j - x_i), l = sqrt(|x_j - x_i|² + eps²) with
  jaxplush's softening eps = LENGTH_EPS x the shortest rest edge, rounded to a power of two;
* gas P = nRT / max(V, VOLUME_EPS V0) (jaxplush's volume clamp), V by signed tetrahedra (against the
  first vertex, as jaxplush does, which keeps float32 cancellation small), P (b - a) x (c - a) / 6 to
  each corner of each face (= P A n / 3);
* Verlet in jaxplush's difference form: u' = (1 - 1/D) u + (f/m + g) h, x' = x + u' h (D = 0: no
  damping factor), started with u_0 = -a_0 h/2 (the ball starts at rest);
* the projection floor exactly as jaxplush.stepping.constraints: a vertex that ends the step below
  the floor H gets y = H and the half-step velocity (H - y_old) / h, i.e. its previous position is
  moved too (it stops; restitution 0).

Implementations: jaxplush float32 (one compiled ``jaxplush.rollout`` scan, as bench_step.py) and
float64 (``jax_enable_x64`` in a child process); Taichi float32 (``ti.cpu``) with one kernel per step
called from a Python loop, serial (``ti.loop_config(serialize=True)`` on every loop) and parallel
(Taichi's default over all cores), and serial with all steps inside one kernel call (a serialised
outer step loop; Taichi parallelises only outermost loops, so that form is serial by nature); numpy
float32 (a control); and a vectorised numpy float64 reference. Every run starts from the same float64
state, rounded to its width. Positions are compared with the reference after the timed N steps and
after a longer "landing run" (default 0.3 s simulated) through the impact on the floor. jaxplush
float64 matches the reference to round-off (~1e-12 m) through the impact; the float32 runs stay within
~1e-5 m before it, and the impact amplifies float32 rounding to ~1e-4 m in every float32
implementation alike (numpy float32 included), so that column measures float32, not a model mismatch.

Taichi is not a jaxplush dependency; install it for this benchmark only (``pip install taichi``).
Without it the script says so and exits 0.

Usage: python benchmarks/bench_peers.py [--sizes 3,4] [--steps 1000] [--repeats 5]
"""

import argparse
import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

#: Simulated time of the correctness run when --check-steps is not given: the ball (bottom at 0.2 m)
#: lands at about 0.2 s, so 0.3 s covers the impact and the floor projection.
CHECK_TIME = 0.3


# --------------------------------------------------------------------------- the model, in numpy

class Model:
    """The model in vectorised numpy, in float64 (the reference) or float32 (a control: a third float32
    implementation), with its constants taken from a jaxplush Scene."""

    def __init__(self, scene, dt, damping=0.0, dtype=np.float64):
        from jaxplush.model.forces import softening_length
        from jaxplush.types import GAS_CONSTANT, VOLUME_EPS
        assert scene.n_objects == 1
        self.x0 = np.asarray(scene.vertices, np.float64)
        self.faces = np.asarray(scene.faces, np.int64)
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        self.edges = np.unique(np.sort(e, axis=1), axis=0)
        self.rest = np.linalg.norm(self.x0[self.edges[:, 1]] - self.x0[self.edges[:, 0]], axis=1)
        self.eps2 = softening_length(self.rest.min()) ** 2
        p = scene.params
        self.k = float(p.k_structural[0])
        self.mass = float(p.total_weight[0]) / len(self.x0)
        self.nrt = float(p.nmol[0]) * GAS_CONSTANT * float(scene.temperature)
        self.gravity = np.asarray(scene.gravity, np.float64)
        self.floor = float(scene.floor)
        self.dt = float(dt)
        self.damping = float(damping)
        self.keep = 1.0 - 1.0 / self.damping if self.damping > 0 else 1.0
        self.n = len(self.x0)
        self.v_rest = self._volume(self.x0)
        self.v_clamp = VOLUME_EPS * self.v_rest
        self._set_precision(dtype)

    def _set_precision(self, dtype):
        """The constants in the working precision ``dtype``."""
        self.dtype = np.dtype(dtype)
        c = self.dtype.type
        self._rest, self._g = self.rest.astype(dtype), self.gravity.astype(dtype)
        self._k, self._eps2, self._nrt, self._vc = c(self.k), c(self.eps2), c(self.nrt), c(self.v_clamp)
        self._inv_m, self._h, self._keep, self._H = c(1.0) / c(self.mass), c(self.dt), c(self.keep), c(self.floor)

    def as_dtype(self, dtype):
        """A copy of this model computing in ``dtype``."""
        m = Model.__new__(Model)
        m.__dict__.update(self.__dict__)
        m._set_precision(dtype)
        return m

    def _volume(self, x):
        r = x - x[:1]
        a, b, c = r[self.faces[:, 0]], r[self.faces[:, 1]], r[self.faces[:, 2]]
        return np.sum(np.einsum("fi,fi->f", a, np.cross(b, c))) / x.dtype.type(6.0)

    def force(self, x):
        n, t = self.n, self.dtype
        i, j = self.edges[:, 0], self.edges[:, 1]
        d = x[j] - x[i]
        inv_l = t.type(1.0) / np.sqrt(np.einsum("ei,ei->e", d, d) + self._eps2)
        fe = (self._k * (t.type(1.0) - self._rest * inv_l))[:, None] * d
        # np.bincount sums in float64 whatever the input; each vertex's few terms are then rounded once
        f = np.stack([np.bincount(i, fe[:, c], n) - np.bincount(j, fe[:, c], n) for c in range(3)], axis=1)
        p = self._nrt / max(self._volume(x), self._vc)
        a, b, c = x[self.faces[:, 0]], x[self.faces[:, 1]], x[self.faces[:, 2]]
        fa = (p / t.type(6.0)) * np.cross(b - a, c - a)
        idx = self.faces.reshape(-1)
        for c in range(3):
            f[:, c] += np.bincount(idx, np.repeat(fa[:, c], 3), n)
        return f.astype(t)

    def accel(self, x):
        return self.force(x) * self._inv_m + self._g

    def initial_state(self):
        """(x_0, u_0) in float64: at rest, u_0 = -a_0 h/2 (jaxplush's verlet_start). Every
        implementation starts from this state, rounded to its precision."""
        ref = self if self.dtype == np.float64 else self.as_dtype(np.float64)
        return ref.x0.copy(), -0.5 * ref.dt * ref.accel(ref.x0)

    def step(self, x, u, contacts=None):
        h = self._h
        u = self._keep * u + self.accel(x) * h if self.damping > 0 else u + self.accel(x) * h
        xn = x + u * h
        below = xn[:, 1] < self._H
        if contacts is not None:
            contacts.append(int(below.sum()))
        u[:, 1] = np.where(below, (self._H - x[:, 1]) / h, u[:, 1])
        xn[:, 1] = np.maximum(xn[:, 1], self._H)
        return xn, u

    def run(self, x, u, steps, contacts=None):
        """``steps`` steps from (x, u) (cast to the working precision); ``contacts``, a list, gets the
        number of floor projections per step."""
        x, u = np.array(x, self.dtype), np.array(u, self.dtype)
        for _ in range(steps):
            x, u = self.step(x, u, contacts)
        return x, u


def ball(sub):
    from bench_step import ball_scene
    return ball_scene(sub)


def check_steps(args, dt):
    return args.check_steps or max(args.steps, int(np.ceil(CHECK_TIME / dt)))


# --------------------------------------------------------------------------- jaxplush

def jaxplush_runs(scene, model, steps, n_check, repeats):
    """(compile s, median steps/s, x after ``steps``, x after ``n_check`` steps, max |u_0 - jaxplush's
    init_fn u_0|), in the process's float width (float64 with jax_enable_x64)."""
    import jax
    import jaxplush
    from jaxplush.model.forces import Terms
    dtype = np.dtype(jax.numpy.result_type(float))
    p = scene.params._replace(damping=np.array([model.damping]))
    sim = jaxplush.make_simulator(scene, model.dt, terms=Terms.for_scene(scene, p))
    p = jax.tree_util.tree_map(lambda a: jax.numpy.asarray(a, dtype), p)
    x0, u0 = model.initial_state()
    init_diff = float(np.max(np.abs(np.asarray(sim.init_fn(p).v, np.float64) - u0)))
    s = jaxplush.State(jax.numpy.asarray(x0, dtype), jax.numpy.asarray(u0, dtype))
    t0 = time.perf_counter()
    jax.block_until_ready(jaxplush.rollout(sim, p, s, 1, steps))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jaxplush.rollout(sim, p, s, 1, steps)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
        assert not out[2].failed
    x_steps = np.asarray(out[0].x, np.float64)
    x_check = x_steps
    if n_check != steps:
        final, _, health = jaxplush.rollout(sim, p, s, 1, n_check)      # after the timing: its compile is apart
        assert not health.failed
        x_check = np.asarray(final.x, np.float64)
    return compile_s, steps / statistics.median(times), x_steps, x_check, init_diff


def x64_worker(args):
    """Child process: jaxplush in float64 for every size; writes a JSON of results to args.worker_out."""
    import jax
    jax.config.update("jax_enable_x64", True)
    out = {}
    for sub, dt in zip(args.sizes.split(","), args.worker_dts.split(",")):
        scene = ball(int(sub))
        model = Model(scene, float(dt), args.damping)
        n_check = check_steps(args, model.dt)
        c, sps, x_steps, x_check, init_diff = jaxplush_runs(scene, model, args.steps, n_check, args.repeats)
        np.save(f"{args.worker_out}.{sub}.npy", np.stack([x_steps, x_check]))
        out[sub] = dict(compile_s=c, steps_per_s=sps, init_diff=init_diff)
    with open(args.worker_out, "w") as fh:
        json.dump(out, fh)


# --------------------------------------------------------------------------- Taichi

class TaichiSim:
    """The model in Taichi float32: one kernel per step (serial or parallel loops) and a kernel that
    runs n steps in a serialised outer loop."""

    def __init__(self, ti, model, serial):
        self.ti = ti
        m = model
        V, E, F = m.n, len(m.edges), len(m.faces)
        f32 = ti.f32
        x = self.x = ti.Vector.field(3, f32, V)
        u = self.u = ti.Vector.field(3, f32, V)
        f = ti.Vector.field(3, f32, V)
        xo = ti.Vector.field(3, f32, V)
        edges = ti.Vector.field(2, ti.i32, E)
        rest = ti.field(f32, E)
        faces = ti.Vector.field(3, ti.i32, F)
        vol = ti.field(f32, ())
        edges.from_numpy(m.edges.astype(np.int32))
        rest.from_numpy(m.rest.astype(np.float32))
        faces.from_numpy(m.faces.astype(np.int32))
        # compile-time constants (float32, as jaxplush's float32 run casts them)
        k, eps2, nrt, v_clamp = (float(np.float32(a)) for a in (m.k, m.eps2, m.nrt, m.v_clamp))
        inv_m = float(np.float32(1.0) / np.float32(m.mass))
        h, keep, H = float(np.float32(m.dt)), float(np.float32(m.keep)), float(np.float32(m.floor))
        gx, gy, gz = (float(np.float32(g)) for g in m.gravity)
        damped = m.damping > 0

        @ti.func
        def one_step():
            ti.loop_config(serialize=serial)
            for i in range(V):
                f[i] = ti.Vector([0.0, 0.0, 0.0])
                xo[i] = x[i]
            ti.loop_config(serialize=serial)
            for e in range(E):                                   # springs
                a, b = edges[e][0], edges[e][1]
                d = x[b] - x[a]
                inv_l = 1.0 / ti.sqrt(d.dot(d) + eps2)
                fe = (k * (1.0 - rest[e] * inv_l)) * d
                f[a] += fe
                f[b] -= fe
            vol[None] = 0.0
            ti.loop_config(serialize=serial)
            for t in range(F):                                   # volume (a reduction)
                r = x[0]
                a, b, c = x[faces[t][0]] - r, x[faces[t][1]] - r, x[faces[t][2]] - r
                vol[None] += a.dot(b.cross(c)) / 6.0
            p6 = nrt / ti.max(vol[None], v_clamp) / 6.0
            ti.loop_config(serialize=serial)
            for t in range(F):                                   # pressure, a third of P A n per corner
                ia, ib, ic = faces[t][0], faces[t][1], faces[t][2]
                fa = p6 * (x[ib] - x[ia]).cross(x[ic] - x[ia])
                f[ia] += fa
                f[ib] += fa
                f[ic] += fa
            ti.loop_config(serialize=serial)
            for i in range(V):                                       # damped Verlet, gravity, floor
                acc = f[i] * inv_m + ti.Vector([gx, gy, gz])
                un = u[i] + acc * h
                if ti.static(damped):
                    un = keep * u[i] + acc * h
                xn = x[i] + un * h
                if xn[1] < H:
                    un[1] = (H - xo[i][1]) / h
                    xn[1] = H
                u[i] = un
                x[i] = xn

        @ti.kernel
        def step():
            one_step()

        @ti.kernel
        def run(n: ti.i32):
            ti.loop_config(serialize=True)
            for _ in range(n):
                one_step()

        self.step, self.run_kernel = step, run

    def set_state(self, x, u):
        self.x.from_numpy(x.astype(np.float32))
        self.u.from_numpy(u.astype(np.float32))

    def positions(self):
        return self.x.to_numpy().astype(np.float64)

    def loop(self, steps, in_kernel):
        if in_kernel:
            self.run_kernel(steps)
        else:
            for _ in range(steps):
                self.step()
        self.ti.sync()


def taichi_runs(ti, model, serial, in_kernel, steps, n_check, repeats):
    """(compile s, median steps/s, x after ``steps``, x after ``n_check`` steps)."""
    sim = TaichiSim(ti, model, serial)
    x0, u0 = model.initial_state()
    sim.set_state(x0, u0)
    t0 = time.perf_counter()
    sim.loop(1, in_kernel)                     # first call: JIT compile + one step
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        sim.set_state(x0, u0)
        t0 = time.perf_counter()
        sim.loop(steps, in_kernel)
        times.append(time.perf_counter() - t0)
    x_steps = sim.positions()
    x_check = x_steps
    if n_check != steps:
        sim.set_state(x0, u0)
        sim.loop(n_check, in_kernel)
        x_check = sim.positions()
    return compile_s, steps / statistics.median(times), x_steps, x_check


def numpy_runs(model, steps, n_check, repeats, contacts=None):
    """(0, median steps/s, x after ``steps``, x after ``n_check`` steps); numpy compiles nothing."""
    x0, u0 = model.initial_state()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        x_steps, _ = model.run(x0, u0, steps)
        times.append(time.perf_counter() - t0)
    x_check = model.run(x0, u0, n_check, contacts)[0] if (n_check != steps or contacts is not None) else x_steps
    return 0.0, steps / statistics.median(times), x_steps.astype(np.float64), x_check.astype(np.float64)


# --------------------------------------------------------------------------- main

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="3,4", help="icosphere subdivisions (2,3,4 = 162, 642, 2562 vertices)")
    ap.add_argument("--steps", type=int, default=1000, help="steps per timed rollout")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--check-steps", type=int, default=0,
                    help=f"steps of the correctness run (default: --steps or {CHECK_TIME} s, whichever is longer)")
    ap.add_argument("--dt", type=float, default=0.0, help="time step (default 0.5 x estimate_stable_dt, as bench_step.py)")
    ap.add_argument("--damping", type=float, default=0.0, help="the report's Verlet damping D (0: none, the bench scene)")
    ap.add_argument("--worker-out", help=argparse.SUPPRESS)
    ap.add_argument("--worker-dts", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker_out:
        return x64_worker(args)

    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
    os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
    os.environ.setdefault("TI_LOG_LEVEL", "warn")
    try:
        import taichi as ti
    except ImportError:
        print("bench_peers.py needs Taichi, which is not a jaxplush dependency. Install it for this "
              "benchmark only:\n    pip install taichi        # taichi 1.7.4 supports Python 3.8-3.12\n"
              "then rerun: python benchmarks/bench_peers.py")
        return 0

    import jax
    import jaxplush
    sizes = [int(s) for s in args.sizes.split(",")]
    scenes, models = {}, {}
    for sub in sizes:
        scenes[sub] = ball(sub)
        dt = args.dt
        if not dt:
            sim0 = jaxplush.make_simulator(scenes[sub], 1e-4)
            dt = 0.5 * jaxplush.estimate_stable_dt(sim0, sim0.params()).dt_max
        models[sub] = Model(scenes[sub], dt, args.damping)

    # jaxplush float64 in a child process (jax_enable_x64 is process-wide); run before any timing here
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "x64.json")
        cmd = [sys.executable, os.path.abspath(__file__), "--sizes", args.sizes, "--steps", str(args.steps),
               "--repeats", str(args.repeats), "--check-steps", str(args.check_steps), "--damping", str(args.damping),
               "--worker-out", out, "--worker-dts", ",".join(repr(models[s].dt) for s in sizes)]
        subprocess.run(cmd, check=True)
        with open(out) as fh:
            x64 = json.load(fh)
        x64_x = {s: np.load(f"{out}.{s}.npy") for s in sizes}

    with contextlib.redirect_stdout(sys.stderr):       # ti.init prints its arch to stdout
        ti.init(arch=ti.cpu, default_fp=ti.f32, offline_cache=False)
    threads = os.cpu_count()
    cache = "on" if os.environ.get("JAXPLUSH_CACHE_DIR") else "off"
    print(f"# jaxplush {jaxplush.__version__} (jax {jax.__version__}, XLA CPU, persistent cache {cache}); "
          f"taichi {'.'.join(map(str, ti.__version__))} (ti.cpu, offline cache off, parallel = {threads} threads); "
          f"numpy {np.__version__}; {os.cpu_count()} cores, {platform.processor() or platform.machine()}. "
          f"Timed: {args.steps}-step rollouts, median of {args.repeats}; compile = first call. "
          f"Float widths as named per row; every run starts from the same float64 state, rounded. "
          f"Damping D = {args.damping:g}.")
    notes = []
    print(f"| vertices | implementation | compile (s) | steps/s | vs jaxplush | max |Δx| vs numpy float64 after "
          f"N = {args.steps} steps (m) | max |Δx| vs numpy float64 after the landing run (m) |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for sub in sizes:
        scene, model = scenes[sub], models[sub]
        n_check = check_steps(args, model.dt)
        contacts = []
        ref = numpy_runs(model, args.steps, n_check, args.repeats, contacts)
        contacts = np.asarray(contacts)
        hit = np.nonzero(contacts)[0]
        floor_note = (f"the floor projection acts from step {hit[0] + 1} to {hit[-1] + 1} ({int(contacts.sum())} "
                      f"vertex projections)" if len(hit) else "the ball never reaches the floor")
        notes.append(f"{model.n} vertices: dt = {model.dt:.4g} s; landing run {n_check} steps = "
                     f"{n_check * model.dt:.3f} s, {floor_note}; |u_0 numpy - jaxplush init_fn| in float64 = "
                     f"{x64[str(sub)]['init_diff']:.1e} m/s")
        r = x64[str(sub)]
        rows = [("jaxplush float32 (lax.scan)",) + jaxplush_runs(scene, model, args.steps, n_check, args.repeats)[:4],
                ("jaxplush float64 (lax.scan, x64 process)", r["compile_s"], r["steps_per_s"], *x64_x[sub])]
        for label, serial, in_kernel in (("taichi float32 serial, kernel per step", True, False),
                                         ("taichi float32 serial, all steps in one kernel", True, True),
                                         (f"taichi float32 parallel ({threads} threads), kernel per step", False, False)):
            rows.append((label,) + taichi_runs(ti, model, serial, in_kernel, args.steps, n_check, args.repeats))
        rows.append(("numpy float32 (control)",) + numpy_runs(model.as_dtype(np.float32), args.steps, n_check,
                                                               args.repeats))
        rows.append(("numpy float64 (reference)",) + ref)
        base = rows[0][2]
        for label, c, sps, x_steps, x_check in rows:
            e1 = np.max(np.linalg.norm(x_steps - ref[2], axis=1))
            e2 = np.max(np.linalg.norm(x_check - ref[3], axis=1))
            print(f"| {model.n} | {label} | {c:.2f} | {sps:,.0f} | {sps / base:.2f}x | {e1:.1e} | {e2:.1e} |",
                  flush=True)
    print()
    for note in notes:
        print(f"- {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
