"""Parameter recovery of the default fit, case by case, as a user runs it.

Scenes (``jaxplush.fitting.targets.scenarios``), each dropped 0.2 m onto a floor, 0.12 kg, gas at 1800 Pa rest
pressure, k = 420 N/m:

* ``ball``: a 642-vertex icosphere with the report's per-step damping 2000;
* ``torus``: a 640-vertex torus lying flat, edge dashpot 0.1 N s/m;
* ``bean``: a 642-vertex bent ellipsoid dropped tilted by 30 degrees, edge dashpot 0.1 N s/m;
* ``ball2562``: the ball at 2562 vertices.

Targets: 3000 steps of 2e-4 s saved every 50 steps (``jaxplush simulate``), as positions, and as
point clouds of 400 points per frame with 2 mm noise. Starts: every corner of x0.5 / x2 in k,
the damping parameter and nmol. Every case runs ``jaxplush-fit START.obj TARGET.h5 --out
FIT.h5`` with no other options, in a fresh process (import and compile included, with the persistent
compilation cache off, as on a user's first fit of a scene); it passes when
the fit says converged (exit 0) and every parameter is within 1% (positions) or 3% (points) of
the truth, within 60 s (240 s at 2562 vertices). A failed case is listed, never dropped.

Random scenes (``--random N --seed S``): N cases drawn by ``jaxplush.fitting.targets.scenarios.draw_case``,
each from its own generator ``numpy.random.default_rng([S, i])`` (case i is the same whatever N):
ball, torus, bean, cushion or capsule at about 162 or 642 vertices, 1 to 3 objects (stacked and
dropped onto a floor, or hanging side by side from a pinned vertex; soft-soft contact on with
several), the report's damping, dashpot, drag or a mix of two, floor friction in half the floor
scenes, heights, tilts, masses, and a start drawn log-uniformly in x0.5..x2 for every fitted
parameter (the default of jaxplush-fit: k_structural, the damping model's and nmol) of every
object (a truth that cannot be simulated at any dt, e.g. a coarse torus crushed inside out
under a stack, is drawn again, at most twice, and the summary lists it). dt is the largest of 5e-4, 4e-4, 2.5e-4, 2e-4, 1.25e-4, 1e-4, 5e-5 s below 0.8 of the truth's
closed-form stability bound (``jaxplush.stepping.stability.bound``; the next one down, twice at
most, when the truth's target blows up all the same), the target runs the case's
duration (the top object lands and bounces; 0.5 s hanging) with about 50 frames, as exact
positions or as point clouds of 400 points per frame with 2 mm noise. Each fit is
``jaxplush-fit START.obj TARGET.h5 --out FIT.h5 --quiet`` (``jaxplush.fitting.cli.main``),
each case in a fresh Python process with an empty persistent compilation cache of its own, as
on a user's first fit (``--in-process``: all in this one, sharing the cache, so a case can load
programs of an earlier one of its size bucket), stopped (Ctrl-C, as a user would)
once it has run ``--stop-after`` times its time budget (120 s for one object, 300 s for several).
A case is recovered when the fit says converged (exit 0) and every fitted parameter of every
object is within 1% (positions) or 3% (points) of the truth, within the budget; a failed case
gets a reason: floor (status at_floor), horizon (FIT.h5's predictability says the target is not
predictable over its length), identifiability (status undetermined, or the fit's identifiability
report has undetermined parameters, or a parameter outside the tolerance has a standard error of
at least half the tolerance: the target does not determine it that well), time (over the budget),
or other (the status). A scene
damped by both the report's ``damping`` and air ``drag`` fits both, which no target can tell
apart (both decay every velocity uniformly): the fit should end ``undetermined``, and the row
also gives the error of the combined rate 1/(D dt) + drag, which is what the target
determines.

Usage: python benchmarks/bench_recovery.py [--scenes ball,torus,bean,ball2562] [--kinds positions,points]
           [--corners all|N] [--json results.jsonl]
       python benchmarks/bench_recovery.py --random N [--seed S] [--max-vertices V] [--max-objects O]
           [--kinds positions,points] [--steps N] [--dt DT] [--stop-after F] [--json results.jsonl [--resume]]
           [--oracle oracle.jsonl]
       python benchmarks/bench_recovery.py --random N [--seed S] ... --oracle-only --json oracle.jsonl [--resume]

The oracle (``--oracle-only``; benchmarks/oracle.py) is computed at the truth before any fit
runs and independent of the fitter: the Cramér-Rao sd of every fitted parameter from segments
restarted from the true states (float64 sensitivities; the noise of the target: a float32 twin's
rounding for positions, the 2 mm of a cloud). A case is determinable when every parameter's sd
is at most half the tolerance (a damping+drag pair by its combined rate). With ``--oracle FILE``
the summary also judges the fits against it: the determinable cases recovered, and the excluded
ones with their reasons.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import itertools
import math
import signal
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings

import h5py
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

SCENES = {
    "ball": dict(shape="ball", subdivisions=3, damping=2000.0, dashpot=None),
    "torus": dict(shape="torus", subdivisions=3, damping=None, dashpot=0.1),
    "bean": dict(shape="bean", subdivisions=3, damping=None, dashpot=0.1, tilt_deg=30.0),
    "ball2562": dict(shape="ball", subdivisions=4, damping=2000.0, dashpot=None),
}
TOLERANCE = {"positions": 0.01, "points": 0.03}
TIME_LIMIT = {642: 60.0, 640: 60.0, 2562: 240.0}
STEPS, DT, SAVE_EVERY = 3000, 2e-4, 50


def _damp_name(spec):
    return "damping" if spec["damping"] is not None else "dashpot"


def make_case_files(d, name, kind):
    """Write the truth scene and the target of one scene and target kind; return (truth scene, target path)."""
    import jaxplush
    from jaxplush.fitting.targets.scenarios import drop_scene_text
    from jaxplush.fitting.targets import make_target
    spec = dict(SCENES[name])
    text = drop_scene_text(spec.pop("shape"), spec.pop("subdivisions"), **spec)
    truth_path = os.path.join(d, f"{name}_truth.obj")
    with open(truth_path, "w") as fh:
        fh.write(text)
    truth = jaxplush.load_scene(truth_path)
    target = os.path.join(d, f"{name}_{kind}.h5")
    if kind == "positions":
        subprocess.run([sys.executable, "-m", "jaxplush", "simulate", truth_path, "--steps", str(STEPS), "--dt", str(DT),
                        "--save-every", str(SAVE_EVERY), "--out", target, "--quiet"], check=True, capture_output=True)
    else:
        make_target(truth, STEPS, DT, SAVE_EVERY, point_cloud=True, n_points=400, noise=0.002, seed=1).save(target, truth)
    return truth, target


def start_scene(d, name, truth, factors):
    from jaxplush.scene.write import format_scene
    spec = SCENES[name]
    dn = _damp_name(spec)
    p = truth.params
    o = truth.objects[0]
    obj = dict(name=o.name, vertices=truth.vertices, faces=truth.faces, total_weight=float(p.total_weight[0]),
               k_structural=float(p.k_structural[0]) * factors[0], nmol=float(p.nmol[0]) * factors[2])
    obj[dn] = float(getattr(p, dn)[0]) * factors[1]
    text = format_scene([obj], gravity=truth.gravity, floor=truth.floor, temperature=truth.temperature,
                        header=f"{name}: start at k x{factors[0]:g}, {dn} x{factors[1]:g}, nmol x{factors[2]:g}")
    path = os.path.join(d, f"{name}_start_{'_'.join(f'{f:g}' for f in factors)}.obj")
    with open(path, "w") as fh:
        fh.write(text)
    return path


def _shooting_record(f):
    """How a FIT.h5's fit shot: ``segment_frames`` (0: one rollout), ``fitted_frames`` (the frames
    its result was fitted over and judged on: fewer than the target's where the fit cut it at a
    predictable horizon), ``horizon_refit`` (whether it fitted the frames its first values predict
    again, ``fitter._within_horizon``) and, where multiple shooting's own bias was taken off the
    fitted values, ``shooting_bias`` (relative, per fitted value)."""
    if "shooting" not in f:
        return {}
    g = f["shooting"]
    out = dict(segment_frames=int(g.attrs["segment_frames"]))
    if "fitted/positions" in f:
        out["fitted_frames"] = int(f["fitted/positions"].shape[0])
    out["horizon_refit"] = any(str(w).startswith("fitted again over the first ")
                               for w in json.loads(f.attrs.get("warnings", "[]")))
    if "bias" in g.attrs:
        out["shooting_bias"] = [float(b) for b in np.ravel(g.attrs["bias"])]
    return out


def run_case(d, name, kind, truth, target, factors, extra=()):
    """Fit one case by ``jaxplush-fit`` (``extra``: more of its arguments) in a cold process."""
    start = start_scene(d, name, truth, factors)
    out = os.path.join(d, "FIT.h5")
    if os.path.exists(out):
        os.remove(out)
    t = time.perf_counter()
    # cold: no persistent compilation cache, so every case compiles as a user's first fit does
    env = dict(os.environ, JAXPLUSH_CACHE_DIR="off")
    proc = subprocess.run([sys.executable, "-m", "jaxplush.fitting.cli", start, target, "--out", out, "--quiet", *extra],
                          capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    spec = SCENES[name]
    names = ("k_structural", _damp_name(spec), "nmol")
    row = dict(scene=name, kind=kind, vertices=truth.n_vertices, factors=list(factors), wall=wall,
               exit=proc.returncode)
    if not os.path.exists(out):
        row.update(status="no FIT.h5", errors={}, max_error=float("inf"), message=proc.stderr.strip()[-300:])
        return row
    with h5py.File(out, "r") as f:
        fitted = {n: float(f["params"][n][0]) for n in names}
        row["status"] = str(f.attrs["status"])
        row["message"] = str(f.attrs.get("reason", ""))
        row.update(_shooting_record(f))
    errors = {n: fitted[n] / float(getattr(truth.params, n)[0]) - 1.0 for n in names}
    row.update(errors=errors, max_error=max(abs(e) for e in errors.values()))
    limit = TIME_LIMIT.get(truth.n_vertices, 60.0)
    row["passed"] = bool(row["exit"] == 0 and row["status"] == "converged" and row["max_error"] <= TOLERANCE[kind]
                         and wall <= limit)
    return row


# ----------------------------------------------------------------------------------------------
# Random scenes (--random N)

#: Time budget of one fit, s: one object, several objects.
RANDOM_BUDGET = {1: 120.0, "several": 300.0}
#: The dt ladder of the random cases (the largest below 0.8 of the stability bound).
DT_LADDER = (5e-4, 4e-4, 2.5e-4, 2e-4, 1.25e-4, 1e-4, 5e-5)
#: Frames per target (about).
RANDOM_FRAMES = 50
#: Points per frame and noise of a point-cloud target.
CLOUD_POINTS, CLOUD_NOISE = 400, 0.002
#: Failure reasons, in the order they are tested.
REASONS = ("floor", "horizon", "identifiability", "time", "other")


def budget(case):
    return RANDOM_BUDGET[1] if case["n_objects"] == 1 else RANDOM_BUDGET["several"]


#: Draws of one random case in all: a truth that cannot be simulated at any dt of the ladder (a
#: coarse torus crushed inside out under a stack, say) is no fitting case; the case is drawn again
#: (from ``default_rng([seed, i, attempt])``), and the row says so.
MAX_DRAWS = 3


def draw_cases(n, seed, **kw):
    """The first ``n`` random cases of ``seed`` (case i from ``default_rng([seed, i])``)."""
    return [redraw(i, seed, 0, **kw) for i in range(n)]


def redraw(index, seed, attempt, **kw):
    """Case ``index`` of ``seed``, draw ``attempt`` (0: ``default_rng([seed, index])``; later ones
    ``default_rng([seed, index, attempt])``)."""
    from jaxplush.fitting.targets.scenarios import draw_case
    key = [seed, index] + ([attempt] if attempt else [])
    case = draw_case(np.random.default_rng(key), **kw)
    case.update(index=index, seed=seed, attempt=attempt, draw_kw=kw)
    return case


def auto_dt(scene):
    """The largest dt of :data:`DT_LADDER` below 0.8 of the closed-form stability bound of ``scene``."""
    import jaxplush
    from jaxplush.stepping import stability
    sim = jaxplush.make_simulator(scene, DT_LADDER[-1])
    limit = 0.8 * stability.bound(sim, sim.params()).dt_max
    fits = [d for d in DT_LADDER if d <= limit]
    return fits[0] if fits else limit / 2


def random_case_files(d, case, *, dt=None, steps=None):
    """Write the case's truth scene, target and start scene under ``d``; return (truth Scene,
    target path, start path). Sets ``case["dt"]``, ``["steps"]``, ``["save_every"]``, ``["dt_retries"]`` (and
    ``["contact_capacity"]`` when the truth's contact candidates overflowed the default)."""
    import jaxplush
    from jaxplush.errors import SimulationError
    from jaxplush.fitting.targets.scenarios import case_scene_text, case_start_text
    from jaxplush.fitting.targets import make_target
    tag = f"case{case['index']:03d}"
    truth = jaxplush.parse_scene(case_scene_text(case), f"{tag}_truth.obj")
    given_dt = dt
    dt = dt or auto_dt(truth)
    points = case["kind"] == "points"
    kw = dict(point_cloud=points, n_points=CLOUD_POINTS if points else None, noise=CLOUD_NOISE if points else 0.0,
              seed=1000 * case.get("seed", 0) + case["index"])
    case["dt_retries"] = 0
    while True:
        n = steps or max(1, int(round(case["duration"] / dt)))
        every = max(1, n // RANDOM_FRAMES)
        case.update(dt=dt, steps=n, save_every=every)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                target = make_target(truth, n, dt, every, **kw)
                break
            except SimulationError as e:
                if truth.n_objects > 1 and "overflowed" in str(e) and not case.get("contact_capacity"):
                    case["contact_capacity"] = int(jaxplush.contact_capacity_needed(truth, n, dt))
                    truth = jaxplush.parse_scene(case_scene_text(case), f"{tag}_truth.obj")
                    continue
                # the truth blew up (the closed-form bound is taken at rest: an impact, floor friction
                # or contact can need less): the next dt of the ladder, twice at most, unless dt was given
                smaller = [x for x in DT_LADDER if x < dt * (1 - 1e-9)]
                if given_dt or case["dt_retries"] >= 2 or not smaller:
                    raise
                dt = smaller[0]
                case["dt_retries"] += 1
    truth_path, target_path, start_path = (os.path.join(d, f"{tag}_{n}") for n in ("truth.obj", "target.h5",
                                                                                   "start.obj"))
    with open(truth_path, "w") as fh:
        fh.write(truth.text)
    target.save(target_path, truth)
    with open(start_path, "w") as fh:
        fh.write(case_start_text(case))
    return truth, target_path, start_path


def cloud_case_at_truth(case):
    """(target, frames (T, V, 3) float32: ``jaxplush.simulate`` of the truth at the target's T
    frames, topology) of a point-cloud case; None for a positions case. For the scripts that
    check the scan residual at the truth (``scan_nearest_check.py``, ``scan_residual_cost.py``)."""
    import jaxplush
    from jaxplush.fitting.targets import load_target
    with tempfile.TemporaryDirectory() as d:
        truth, target_path, _ = random_case_files(d, case)
        target = load_target(target_path, truth)
    if target.points is None:
        return None
    frames = np.asarray(jaxplush.simulate(truth, case["steps"], case["dt"], case["save_every"]).positions,
                        np.float32)
    frames = frames[len(frames) - len(target.points):]      # frame 0 (the start) is not in the target
    return target, frames, jaxplush.make_simulator(truth, case["dt"]).topology


@contextlib.contextmanager
def _deadline(seconds):
    """Raise KeyboardInterrupt (the fit's Ctrl-C: it saves its state and exits 130) after ``seconds``."""
    if not seconds or not math.isfinite(seconds) or not hasattr(signal, "SIGALRM"):
        yield
        return

    def ring(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, ring)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def run_random_case(d, case, *, dt=None, steps=None, stop_after=1.0):
    """Make the case's files, fit it with jaxplush-fit (in this process) and return its record (a dict)."""
    from jaxplush.fitting import cli
    from jaxplush.fitting.io import load_fit
    from jaxplush.fitting.targets.scenarios import case_truth, describe_case
    row = dict(index=case.get("index"), seed=case.get("seed"), description=describe_case(case),
               shapes=[o["shape"] for o in case["objects"]], vertices=[o["vertices"] for o in case["objects"]],
               n_objects=case["n_objects"], damping_model=case["damping_model"], setting=case["setting"],
               pinned=case["setting"] == "pinned", floor=case["setting"] == "floor",
               floor_friction=case.get("floor_friction"), kind=case["kind"], params=list(case["params"]),
               start_factors=case["start"], budget=budget(case))
    t = time.perf_counter()
    try:
        truth, target, start = random_case_files(d, case, dt=dt, steps=steps)
    except Exception as e:
        from jaxplush.errors import SimulationError
        attempt = case.get("attempt", 0) + 1
        if isinstance(e, SimulationError) and dt is None and attempt < MAX_DRAWS:
            # the truth cannot be simulated at any dt of the ladder: no fitting case; draw again
            again = redraw(case["index"], case.get("seed", 0), attempt, **case.get("draw_kw", {}))
            out = run_random_case(d, again, dt=dt, steps=steps, stop_after=stop_after)
            out["redrawn"] = [f"{row['description']}: {str(e)[:160]}"] + out.get("redrawn", [])
            return out
        # a truth that still cannot be simulated: a failed case, never dropped
        row.update(dt=case.get("dt"), steps=case.get("steps"), status="no target", exit=None, wall=0.0,
                   max_error=float("inf"), errors={}, verdict="failed", reason="other",
                   detail=f"target: {type(e).__name__}: {str(e)[:200]}")
        return row
    row.update(dt=case["dt"], steps=case["steps"], save_every=case["save_every"],
               duration=case["steps"] * case["dt"], contact_capacity=case.get("contact_capacity"),
               dt_retries=case.get("dt_retries", 0),
               target_wall=time.perf_counter() - t)
    out = os.path.join(d, f"case{case['index']:03d}_FIT.h5")
    if os.path.exists(out):
        os.remove(out)
    stdout, stderr = io.StringIO(), io.StringIO()
    t = time.perf_counter()
    with _deadline(stop_after * row["budget"] if stop_after else None), \
            contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = cli.main([start, target, "--out", out, "--quiet", *FIT_ARGS])
        except KeyboardInterrupt:   # the deadline rang outside the fit's own handler
            code = cli.EXIT_INTERRUPTED
    wall = time.perf_counter() - t
    row.update(exit=int(code), wall=wall, stopped=code == cli.EXIT_INTERRUPTED)
    lines = [ln for ln in stderr.getvalue().splitlines() if ln.strip()]
    row["stderr_tail"] = lines[-3:]
    fit = load_fit(out) if os.path.exists(out) else None
    truth_values = case_truth(case)
    if fit is None or "params" not in fit:
        row.update(status="no FIT.h5", errors={}, max_error=float("inf"))
    else:
        row["status"] = str(fit["attrs"].get("status"))
        row["message"] = str(fit["attrs"].get("reason", ""))
        with h5py.File(out, "r") as f:
            row.update(_shooting_record(f))
            fitted = np.asarray(f["fitted/positions"], np.float64) if "fitted/positions" in f else None
        if fitted is not None:
            # each frame's misfit at the fitted values (against the oracle's float64 truth twin)
            from jaxplush.fitting.targets import load_target
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                tgt = load_target(target, truth)
            row["fit_rms"] = [float(r) for r in _oracle_module().frame_rms(fitted, tgt, np.asarray(truth.faces))]
            row["frame_times"] = [float(t) for t in np.asarray(tgt.times, np.float64)]
        names = [n for n in case["params"] if n in fit["params"]]
        errors = {f"{n}[{o['name']}]": float(fit["params"][n][j]) / truth_values[n][j] - 1.0
                  for n in names for j, o in enumerate(case["objects"])}
        row["fitted_params"] = names
        row["errors"] = errors
        row["max_error"] = max((abs(e) for e in errors.values()), default=float("inf"))
        if set(names) != set(case["params"]):
            row["detail"] = f"fitted {names}, expected {case['params']}"
        iv, iva = fit.get("intervals"), fit.get("intervals_attrs") or {}
        if iv is not None:
            # the truth inside the reported 95% interval, and inside 4 of its spreads (sd)
            q = float(iva.get("quantile", 1.96))
            sd = dict(zip([str(x) for x in iva.get("labels", [])], np.asarray(iv["sd"], np.float64)))
            off = {k: abs(math.log1p(e)) for k, e in errors.items() if k in sd and e > -1}
            row["interval_method"] = str(iva.get("method", ""))
            if row["interval_method"] == "box":
                # a fit that stopped short of the data: its interval is its search box (no spread);
                # the truth lies in it or not
                at = {str(x): i for i, x in enumerate(iva.get("labels", []))}
                lo, hi, th = (np.asarray(iv[k], np.float64) for k in ("lower", "upper", "theta"))
                row["covered"] = {k: bool(math.log(lo[at[k]]) - 1e-12 <= th[at[k]] - math.log1p(errors[k])
                                          <= math.log(hi[at[k]]) + 1e-12) for k in off}
                row["covered4"] = dict(row["covered"])
            else:
                row["covered"] = {k: bool(v <= q * sd[k]) for k, v in off.items()}
                row["covered4"] = {k: bool(v <= 4 * sd[k]) for k, v in off.items()}
            row["interval_sd"] = {k: float(sd[k]) for k in off}
        pa = fit.get("predictability_attrs")
        if pa is not None:
            row["horizon_time"] = float(pa.get("horizon_time", float("inf")))
            row["floor_rms"] = float(pa.get("floor_rms", float("nan")))
        if "identifiability" in fit:
            if "stderr" in fit["identifiability"]:
                labels_se = list(fit.get("identifiability_attrs", {}).get("labels", []))
                row["stderr"] = {str(lab): float(v) for lab, v in
                                 zip(labels_se, np.asarray(fit["identifiability"]["stderr"], np.float64))}
            det = np.asarray(fit["identifiability"]["determined"], bool)
            labels = list(fit.get("identifiability_attrs", {}).get("labels", range(len(det))))
            und = fit.get("identifiability_attrs", {}).get("undetermined")
            row["undetermined"] = (json.loads(und) if isinstance(und, str) else
                                   [str(lab) for lab, ok in zip(labels, det) if not ok])
            warns = fit.get("identifiability_attrs", {}).get("warnings", "[]")
            warns = json.loads(warns) if isinstance(warns, str) else list(warns)
            # a weak combination ("ill-conditioned ... only the ratio ... is determined") or a poorly
            # determined parameter is flagged too
            row["identifiability_warnings"] = [w for w in warns if "determined" in w or "ill-conditioned" in w]
        if "damping" in names and "drag" in names and row.get("dt"):
            # one effect (uniform velocity decay): what a target determines is the combined rate,
            # 1/(D dt) + drag in the damped Verlet update (jaxplush.fitting.stages.equation_error.damping_rate)
            rate = lambda d, g: 1.0 / (d * row["dt"]) + g  # noqa: E731
            row["combined_rate_errors"] = [
                rate(float(fit["params"]["damping"][j]), float(fit["params"]["drag"][j]))
                / rate(truth_values["damping"][j], truth_values["drag"][j]) - 1.0
                for j in range(len(case["objects"]))]
    verdict(row)
    return row


@functools.lru_cache(maxsize=None)
def _oracle_module():
    """benchmarks/oracle.py (beside this file, whatever sys.path holds), loaded once."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("recovery_oracle", os.path.join(os.path.dirname(
        os.path.abspath(__file__)), "oracle.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run_oracle_case(d, case, *, dt=None, steps=None):
    """The oracle of one random case (``benchmarks/oracle.py``): its target drawn as the fit's
    would be (the same dt, steps and frames; a case drawn again as there), and which of its
    parameters the target determines, computed at the truth. Returns its record (a dict)."""
    from jaxplush.errors import SimulationError
    from jaxplush.fitting.targets.scenarios import describe_case
    oracle = _oracle_module()
    row = dict(index=case.get("index"), seed=case.get("seed"), description=describe_case(case),
               n_objects=case["n_objects"], kind=case["kind"], params=list(case["params"]))
    t = time.perf_counter()
    try:
        truth, target_path, _ = random_case_files(d, case, dt=dt, steps=steps)
    except SimulationError:
        attempt = case.get("attempt", 0) + 1
        if dt is None and attempt < MAX_DRAWS:
            return run_oracle_case(d, redraw(case["index"], case.get("seed", 0), attempt,
                                             **case.get("draw_kw", {})), dt=dt, steps=steps)
        row.update(oracle=None, case_determinable=False, oracle_reason="the truth cannot be simulated")
        return row
    from jaxplush.fitting.targets import load_target
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        target = load_target(target_path, truth)
        o = oracle.oracle_case(truth, case, dt=case["dt"], steps=case["steps"], every=case["save_every"],
                               kind=case["kind"], n_points=CLOUD_POINTS, noise=CLOUD_NOISE,
                               tolerance=TOLERANCE[case["kind"]], target=target)
    row.update(attempt=case.get("attempt", 0), dt=case["dt"], steps=case["steps"], oracle=o,
               case_determinable=o["case_determinable"], oracle_reason=o["reason"],
               oracle_wall=time.perf_counter() - t)
    return row


def oracle_verdict(row, orc):
    """With the case's oracle record ``orc`` (``--oracle FILE``): set ``row["determinable"]`` and
    ``row["judged"]`` ("recovered": every quantity the oracle judges within the tolerance, a
    damping+drag pair by its combined rate, the fit ended converged, or undetermined only in
    that pair, exit 0, in time; "excluded": the oracle found the case not determinable; else
    "failed")."""
    tol = TOLERANCE[row["kind"]]
    o = (orc or {}).get("oracle") or {}
    row["determinable"] = bool(orc and orc.get("case_determinable"))
    row["oracle_reason"] = (orc or {}).get("oracle_reason") or ("no oracle record" if not orc else None)
    if not row["determinable"]:
        row["judged"] = "excluded"
        return row
    errors = dict(row.get("errors") or {})
    damping = [k for k in errors if k.startswith("damping[")]       # in the objects' order
    for lab, e in zip(damping, row.get("combined_rate_errors") or []):
        errors[f"rate[{lab[len('damping['):-1]}]"] = e
    judged = o.get("determinable", {})
    errs = [abs(errors.get(k, math.inf)) for k in judged]
    row["judged_error"] = max(errs, default=math.inf)
    pair = bool(row.get("combined_rate_errors"))
    und = set(row.get("undetermined") or [])
    status_ok = row.get("status") == "converged" or (
        pair and row.get("status") == "undetermined" and all(k.startswith(("damping[", "drag[")) for k in und))
    in_time = row.get("wall", math.inf) <= row["budget"] and not row.get("stopped")
    ok = row.get("exit") == 0 and status_ok and row["judged_error"] <= tol and in_time
    row["judged"] = "recovered" if ok else "failed"
    twin_ratio(row, orc)
    return row


#: Several objects in contact: the frames re-simulated at the fitted values match the target,
#: within the fit's horizon, to at most this many times the RMS of the truth's float64 twin.
TWIN_RATIO = 1.25


def twin_ratio(row, orc):
    """Set ``row["twin_ratio"]``: the RMS misfit of the fitted frames (``fit_rms``) over that of the
    oracle's float64 truth twin (``twin_rms``), over the frames within the fit's horizon (every
    frame when it has none; a fit cut at a predictable horizon: over its frames, the target's first).
    None when either is missing."""
    fit, twin = row.get("fit_rms"), ((orc or {}).get("oracle") or {}).get("twin_rms")
    times = row.get("frame_times")
    if not fit or not twin or not times or len(fit) > min(len(twin), len(times)):
        row["twin_ratio"] = None
        return None
    twin, times = twin[:len(fit)], times[:len(fit)]
    horizon = row.get("horizon_time", math.inf)
    keep = [i for i, t in enumerate(times) if t <= horizon * (1 + 1e-9)] or list(range(len(times)))
    f = math.sqrt(sum(fit[i] ** 2 for i in keep) / len(keep))
    w = math.sqrt(sum(twin[i] ** 2 for i in keep) / len(keep))
    row["twin_ratio"] = f / w if w > 0 else math.inf
    row["twin_frames"] = len(keep)
    return row["twin_ratio"]


def verdict(row):
    """Set ``row["verdict"]`` (recovered / failed) and ``row["reason"]`` (None or one of :data:`REASONS`)."""
    tol = TOLERANCE[row["kind"]]
    fit_ok = row.get("exit") == 0 and row.get("status") == "converged" and row.get("max_error", math.inf) <= tol
    in_time = row.get("wall", math.inf) <= row["budget"] and not row.get("stopped")
    length = row.get("steps", 0) * (row.get("dt") or 0.0)
    if fit_ok and in_time:
        row.update(verdict="recovered", reason=None)
        return row
    if fit_ok:
        reason = "time"
    elif row.get("status") == "at_floor":
        reason = "floor"
    elif row.get("status") == "undetermined":
        reason = "identifiability"
    elif row.get("horizon_time", math.inf) <= length * (1 + 1e-9):
        reason = "horizon"
    elif row.get("undetermined") or row.get("identifiability_warnings") or unresolved(row):
        reason = "identifiability"
    elif not in_time:
        reason = "time"
    else:
        reason = "other"
    row.update(verdict="failed", reason=reason)
    return row


def unresolved(row):
    """The parameters outside the tolerance whose standard error (the fit's own, from FIT.h5) is
    at least half the tolerance: the target determines them no better than the tolerance (at about
    2 standard errors), so a converged fit can miss it by the noise alone. Sets ``row["unresolved"]``."""
    tol, se = TOLERANCE[row["kind"]], row.get("stderr") or {}
    out = [k for k, e in (row.get("errors") or {}).items()
           if abs(e) > tol and k in se and not se[k] < tol / 2]
    if out:
        row["unresolved"] = out
    return out


def _factors_text(row):
    return " ".join(f"{n.replace('k_structural', 'k')} " + ",".join(f"x{f:g}" for f in fs)
                    for n, fs in row["start_factors"].items())


def _random_line(row):
    err = row.get("max_error", math.inf)
    why = "" if row["verdict"] == "recovered" else f" ({row['reason']})"
    if row.get("combined_rate_errors"):
        worst = max(abs(e) for e in row["combined_rate_errors"])
        why += f"; damping+drag combined rate {100 * worst:.3g}% off"
    return (f"| {row['index']} | {row['description']} | {row['n_objects']} | {_factors_text(row)} | "
            f"{row.get('dt') or float('nan'):g} x {row.get('steps')} | {row['wall']:.1f} | {row.get('exit')} | "
            f"{row['status']}{' (stopped)' if row.get('stopped') else ''} | {100 * err:.3g}% | "
            f"{row['verdict']}{why} |")


def _summary(rows):
    out = []
    for kind, label in (("positions", "positions"), ("points", "clouds")):
        sel = [r for r in rows if r["kind"] == kind]
        out.append(f"{label} {sum(r['verdict'] == 'recovered' for r in sel)}/{len(sel)}")
    rec = sum(r["verdict"] == "recovered" for r in rows)
    lines = [f"recovered {rec}/{len(rows)} ({', '.join(out)})"]
    pair = [r for r in rows if r.get("combined_rate_errors") is not None]
    if pair:
        told = sum(r.get("status") == "undetermined" for r in pair)
        lines.append(f"damping+drag cases (the pair is one effect, never separately identifiable): {len(pair)}, "
                     f"{told} reported 'undetermined'")
    # the intervals a fit reports (converged, undetermined and, since 2026-12-01, at_floor:
    # jaxplush.fitting.judge.outcome.REPORTED; an earlier at_floor row's box counts as a box), and apart
    # those FIT.h5 keeps for a fit that did not reach the data (not shown)
    def group(r):
        if r.get("status") in ("converged", "undetermined", "at_floor") and r.get("interval_method") != "box":
            return "reported"
        if r.get("interval_method") == "box":
            return "search boxes (the fit stopped short of the data)"
        return "not reported (the fit did not reach the data)"

    for label in ("reported", "search boxes (the fit stopped short of the data)",
                  "not reported (the fit did not reach the data)"):
        cov = [(r, k, c) for r in rows for k, c in (r.get("covered") or {}).items() if group(r) == label]
        if not cov:
            continue
        inside = sum(c for _, _, c in cov)
        wide = [(r, k) for r, k, _ in cov if not r["covered4"][k]]
        what = "their boxes" if label.startswith("search") else "the 95% intervals"
        lines.append(f"calibration, {label}: {inside} of {len(cov)} (case, parameter) truths inside {what} "
                     f"({100 * inside / len(cov):.0f}%); {len(wide)} outside 4 spreads"
                     + "".join(f"\n  case {r['index']} {k}: {100 * r['errors'][k]:+.3g}% against a spread of "
                               f"{100 * r['interval_sd'][k]:.2g}% ({r.get('interval_method')}, {r['status']})"
                               for r, k in wide))
    if any(r.get("covered") for r in rows):
        confident = [r for r in rows if r.get("status") == "converged" and r.get("max_error", math.inf) > TOLERANCE[r["kind"]]]
        lines.append(f"confidently wrong (converged outside tolerance): {len(confident)}"
                     + "".join(f"\n  case {r['index']}: {100 * r['max_error']:.3g}%" for r in confident))
    single = [r for r in rows if r["n_objects"] == 1 and r.get("exit") is not None]
    for lo, hi, label in ((0, 200, "coarse (<= 200 vertices)"), (201, 10 ** 9, "fine (> 200 vertices)")):
        ts = [r["wall"] for r in single if lo <= sum(r["vertices"]) <= hi]
        if ts:
            lines.append(f"single-object fits, {label}: median {float(np.median(ts)):.1f} s over {len(ts)}, "
                         f"max {max(ts):.1f} s")
    several = [r["wall"] for r in rows if r["n_objects"] > 1 and r.get("exit") is not None]
    if several:
        lines.append(f"several-object fits: median {float(np.median(several)):.1f} s over {len(several)}, "
                     f"max {max(several):.1f} s")
    if rows:
        lines.append(f"max time: {max(r['wall'] for r in rows):.1f} s")
    redrawn = [r for r in rows if r.get("redrawn")]
    if redrawn:
        lines.append(f"cases drawn again (their first truth could not be simulated at any dt): {len(redrawn)}")
        for r in redrawn:
            lines += [f"  case {r['index']}: {x}" for x in r["redrawn"]]
    fails = {k: [r for r in rows if r["verdict"] == "failed" and r["reason"] == k] for k in REASONS}
    counts = ", ".join(f"{k} {len(v)}" for k, v in fails.items() if v) or "none"
    lines.append(f"failures by reason: {counts}")
    for k, v in fails.items():
        for r in v:
            extra = ""
            if k == "horizon":
                extra = f", horizon {r.get('horizon_time', float('nan')):.3g} s of {r['steps'] * r['dt']:.3g} s"
            elif k == "identifiability":
                extra = f", undetermined {', '.join(r.get('undetermined', []))}"
                if r.get("unresolved"):
                    extra += ", standard error at least half the tolerance: " + ", ".join(
                        f"{lab} {100 * r['errors'][lab]:+.3g}% +-{100 * r['stderr'][lab]:.2g}%" for lab in r["unresolved"])
            lines.append(f"  {k}: case {r['index']} {r['description']}: exit {r.get('exit')}, {r['status']}, "
                         f"max error {100 * r.get('max_error', math.inf):.3g}%, {r['wall']:.1f} s{extra}"
                         + (f"; {r['detail']}" if r.get("detail") else ""))
    return lines


def _case_in_child(args, case):
    """Run one random case in a fresh Python process (its compiled programs and memory go with it;
    a long run in one process once died of an LLVM out-of-memory while compiling) and return its row."""
    argv = [sys.executable, os.path.abspath(__file__), "--random", str(args.random), "--seed", str(args.seed),
            "--max-objects", str(args.max_objects), "--kinds", args.kinds, "--stop-after", str(args.stop_after),
            "--only", str(case["index"])]
    for flag, val in (("--max-vertices", args.max_vertices), ("--steps", args.steps), ("--dt", args.dt)):
        if val is not None:
            argv += [flag, str(val)]
    if args.no_linear_start:
        argv.append("--no-linear-start")
    if args.polish:
        argv += ["--polish", args.polish]
    if args.oracle_only:
        argv.append("--oracle-only")
    t0 = time.perf_counter()
    # cold: an empty persistent compilation cache of its own, as on a user's first fit (programs
    # that the fit compiles twice load from it; nothing comes from an earlier case of the bucket)
    with tempfile.TemporaryDirectory(prefix="jaxplush-case-cache-") as cache:
        proc = subprocess.run(argv, capture_output=True, text=True, env=dict(os.environ, JAXPLUSH_CACHE_DIR=cache))
    rows = [ln[4:] for ln in proc.stdout.splitlines() if ln.startswith("ROW ")]
    if rows:
        return json.loads(rows[-1])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [""]
    from jaxplush.fitting.targets.scenarios import describe_case
    if args.oracle_only:
        return dict(index=case["index"], seed=case.get("seed"), description=describe_case(case),
                    n_objects=case["n_objects"], kind=case["kind"], oracle=None, case_determinable=False,
                    oracle_reason=f"the oracle's process exited {proc.returncode}: {tail[0][-200:]}")
    return dict(index=case["index"], seed=case.get("seed"), description=describe_case(case),
                n_objects=case["n_objects"], kind=case["kind"], start_factors=case["start"],
                status=f"process exited {proc.returncode}", exit=proc.returncode, wall=time.perf_counter() - t0,
                max_error=math.inf, errors={}, verdict="failed", reason="other", detail=tail[0][-200:])


def _draw_key(args):
    """What identifies a random run's draw of cases (and so which JSON lines ``--resume`` keeps)."""
    return (f"--random {args.random} --seed {args.seed} --max-objects {args.max_objects} --kinds {args.kinds}"
            f" --max-vertices {args.max_vertices} --steps {args.steps} --dt {args.dt}"
            + (" --no-linear-start" if args.no_linear_start else "")
            + (f" --polish {args.polish}" if args.polish else ""))


def _oracle_key(args):
    """What identifies the draw of an oracle run (the fit's options aside; case i of a seed is the
    same whatever N, so an oracle of N cases serves a run of fewer)."""
    return (f"oracle --seed {args.seed} --max-objects {args.max_objects} --kinds {args.kinds}"
            f" --max-vertices {args.max_vertices} --steps {args.steps} --dt {args.dt}")


def _read_lines(path, key):
    """{index: row} of the JSON lines of ``path`` whose draw is ``key`` (a line cut short is skipped)."""
    out = {}
    if path and os.path.exists(path):
        with open(path) as fh:
            for ln in fh:
                try:
                    r = json.loads(ln)
                except ValueError:
                    continue
                if r.get("draw") == key:
                    out[r["index"]] = r
    return out


#: The categories of the recovery table (issue 53): (label, test on a row).
CATEGORIES = (
    ("one object", lambda r: r.get("n_objects") == 1),
    ("two objects", lambda r: r.get("n_objects") == 2),
    ("three objects", lambda r: r.get("n_objects") == 3),
    ("several objects on a floor (contact)", lambda r: r.get("n_objects", 1) > 1 and " floor" in r["description"]),
    ("several objects pinned side by side", lambda r: r.get("n_objects", 1) > 1 and " pinned" in r["description"]),
    ("one object, positions", lambda r: r.get("n_objects") == 1 and r.get("kind") == "positions"),
    ("one object, clouds", lambda r: r.get("n_objects") == 1 and r.get("kind") == "points"),
    ("several objects, positions", lambda r: r.get("n_objects", 1) > 1 and r.get("kind") == "positions"),
    ("several objects, clouds", lambda r: r.get("n_objects", 1) > 1 and r.get("kind") == "points"),
    ("damping and drag both (judged on their rate)", lambda r: "damping+drag" in r["description"]),
)


def category_table(rows):
    """Markdown lines: per category, the cases, those the oracle finds determinable, and of those
    the ones recovered (rows judged by :func:`oracle_verdict`; an oracle-only run has no fits)."""
    fits = any("judged" in r for r in rows)
    head = "| category | cases | determinable |" + (" recovered (of the determinable) |" if fits else "")
    out = ["", head, "|---|---:|---:|" + ("---:|" if fits else "")]
    for label, test in CATEGORIES:
        sel = [r for r in rows if test(r)]
        if not sel:
            continue
        det = [r for r in sel if (r.get("judged") in ("recovered", "failed") if fits
                                  else r.get("case_determinable"))]
        line = f"| {label} | {len(sel)} | {len(det)} |"
        if fits:
            line += f" {sum(r['judged'] == 'recovered' for r in det)} of {len(det)} |"
        out.append(line)
    return out + [""]


def _oracle_summary(rows, oracles):
    """Lines: the oracle's verdicts, and the fits judged against it (``oracle_verdict``)."""
    lines = []
    n = len(rows)
    excluded = [r for r in rows if r.get("judged") == "excluded"]
    det = [r for r in rows if r.get("judged") in ("recovered", "failed")]
    rec = [r for r in det if r["judged"] == "recovered"]
    lines.append(f"oracle: {len(det)} of {n} cases determinable; {len(excluded)} excluded "
                 f"({100 * len(excluded) / max(n, 1):.0f}%; at most 10% allowed)")
    for r in excluded:
        lines.append(f"  excluded: case {r['index']} {r['description']}: {r.get('oracle_reason')}")
    lines += category_table(rows)
    if det:
        lines.append(f"determinable cases recovered: {len(rec)} of {len(det)} ({100 * len(rec) / len(det):.0f}%; "
                     f"the target is at least 95%)")
        for r in det:
            if r["judged"] == "failed":
                lines.append(f"  not recovered: case {r['index']} {r['description']}: {r.get('status')}, exit "
                             f"{r.get('exit')}, judged error {100 * r.get('judged_error', math.inf):.3g}%, "
                             f"{r['wall']:.1f} s ({r.get('reason')})")
    # every case not recovered: a named reason, and a 95% interval that holds the truth
    others = [r for r in rows if r.get("judged") != "recovered"]
    if others:
        named = [r for r in others if r.get("reason") in ("floor", "horizon", "identifiability", "time")]
        held = [r for r in others if r.get("covered") and all(r["covered"].values())]
        lines.append(f"cases not recovered: {len(others)}; with a named reason {len(named)}, with every truth inside "
                     f"its 95% interval {len(held)}")
        for r in others:
            if r not in named or r not in held:
                miss = [k for k, c in (r.get("covered") or {}).items() if not c]
                lines.append(f"  case {r['index']}: reason {r.get('reason')}; "
                             + (f"outside the interval: {', '.join(miss)}" if miss else
                                "no interval" if not r.get("covered") else "every truth inside"))
    several = [r for r in rows if r.get("n_objects", 1) > 1 and r.get("twin_ratio") is not None]
    if several:
        within = [r for r in several if r["twin_ratio"] <= TWIN_RATIO]
        ratios = ", ".join(f"case {r['index']} {r['twin_ratio']:.3g}x" for r in several)
        lines.append(f"several objects: fitted frames within {TWIN_RATIO:g}x the float64 truth twin's RMS (within "
                     f"the horizon): {len(within)} of {len(several)} ({ratios})")
        for r in several:
            if r["twin_ratio"] > TWIN_RATIO:
                lines.append(f"  case {r['index']} {r['description']}: {r['twin_ratio']:.3g}x over "
                             f"{r.get('twin_frames')} frames")
    return lines


def main_oracle(args, cases):
    """``--oracle-only``: the oracle of every case, one JSON line each; fixed before the fits run."""
    key = _oracle_key(args)
    done = _read_lines(args.json, key) if args.resume else {}
    if args.resume:
        print(f"# resumed: {len(done)} of {len(cases)} cases already in {args.json}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for case in cases:
            if case["index"] in done:
                rows.append(done[case["index"]])
                continue
            row = (run_oracle_case(d, case, dt=args.dt, steps=args.steps) if args.in_process
                   else _case_in_child(args, case))
            row["draw"] = key
            rows.append(row)
            o = row.get("oracle") or {}
            sd = {**o.get("sd", {}), **o.get("rate_sd", {})}
            print(f"case {row['index']}: {row['description']}: "
                  + ("determinable" if row.get("case_determinable") else f"not determinable: {row.get('oracle_reason')}")
                  + (f"; sd {', '.join(f'{k} {100 * v:.2g}%' for k, v in sd.items())}; {o.get('segments')} "
                     f"segments of {o.get('frames')} frames; {row.get('oracle_wall', 0):.1f} s" if o else ""),
                  flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(row, default=float) + "\n")
    det = sum(bool(r.get("case_determinable")) for r in rows)
    for line in category_table(rows):
        print(line)
    print(f"oracle: {det} of {len(rows)} cases determinable; {len(rows) - det} excluded "
          f"({100 * (len(rows) - det) / max(len(rows), 1):.0f}%; at most 10% allowed)")
    for r in rows:
        if not r.get("case_determinable"):
            print(f"  excluded: case {r['index']} {r['description']}: {r.get('oracle_reason')}")
    return 0


def main_random(args):
    kinds = tuple(args.kinds.split(","))
    cases = draw_cases(args.random, args.seed, max_vertices=args.max_vertices, max_objects=args.max_objects,
                       kinds=kinds)
    print(f"# {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}; "
          f"{time.strftime('%Y-%m-%d %H:%M')}; --random {args.random} --seed {args.seed}"
          + (f" --max-vertices {args.max_vertices}" if args.max_vertices else "")
          + f" --max-objects {args.max_objects} --kinds {args.kinds}"
          + (" --no-linear-start" if args.no_linear_start else "")
          + (f" --polish {args.polish}" if args.polish else ""), flush=True)
    if args.only is not None:                    # one case, in this process (the parent reads the last line)
        with tempfile.TemporaryDirectory() as d:
            if args.oracle_only:
                row = run_oracle_case(d, cases[args.only], dt=args.dt, steps=args.steps)
            else:
                row = run_random_case(d, cases[args.only], dt=args.dt, steps=args.steps, stop_after=args.stop_after)
        print("ROW " + json.dumps(row, default=float), flush=True)
        return 0
    if args.oracle_only:
        return main_oracle(args, cases)
    oracles = _read_lines(args.oracle, _oracle_key(args)) if args.oracle else None
    if args.oracle and not oracles:
        print(f"# no oracle of this draw in {args.oracle} (run --oracle-only first)", flush=True)
    rows = []
    draw = _draw_key(args)
    done = {}
    if args.resume and args.json and os.path.exists(args.json):
        # the cases of this draw already in the JSON lines (an earlier, stopped run): kept, not run again
        done = _read_lines(args.json, draw)
        print(f"# resumed: {len(done)} of {len(cases)} cases already in {args.json}", flush=True)
    with tempfile.TemporaryDirectory() as d:
        for case in cases:
            if case["index"] in done:
                rows.append(done[case["index"]])
                continue
            if args.in_process:
                row = run_random_case(d, case, dt=args.dt, steps=args.steps, stop_after=args.stop_after)
            else:
                row = _case_in_child(args, case)
            row["draw"] = draw
            rows.append(row)
            print(f"case {row['index']}: {row['description']}, {row['n_objects']} object(s), start "
                  f"{_factors_text(row)}: {row['status']}, exit {row.get('exit')}, {row['wall']:.1f} s, "
                  f"max error {100 * row.get('max_error', math.inf):.3g}%: {row['verdict']}"
                  + (f" ({row['reason']})" if row["reason"] else ""), flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(row, default=float) + "\n")
    if oracles is not None:
        for row in rows:
            oracle_verdict(row, oracles.get(row["index"]))
    print()
    print("| # | scene | objects | start factors | dt x steps | wall s | exit | status | max error | verdict |")
    print("|---:|---|---:|---|---|---:|---:|---|---:|---|")
    for row in rows:
        print(_random_line(row))
    print()
    for line in _summary(rows):
        print(line)
    if oracles is not None:
        for line in _oracle_summary(rows, oracles):
            print(line)
    return 0 if all(r["verdict"] == "recovered" for r in rows) else 1


#: More arguments of every random case's ``jaxplush-fit`` (``--no-linear-start``, ``--polish``).
FIT_ARGS = []


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--kinds", default="positions,points")
    ap.add_argument("--corners", default="all", help="all, the first N corners, or indices I,J,... (0-7)")
    ap.add_argument("--jacobian", default=None, choices=("difference", "forward"),
                    help="the fits' Jacobians (jaxplush-fit --jacobian; default: the fit's default)")
    ap.add_argument("--json", default=None, help="append each case as a JSON line to this file")
    ap.add_argument("--resume", action="store_true", help="--random with --json: keep the cases of the same draw "
                    "already in the JSON file and run only the others (a run stopped part way, or spread over "
                    "sittings)")
    ap.add_argument("--random", type=int, default=None, metavar="N", help="fit N random scenes instead")
    ap.add_argument("--seed", type=int, default=0, help="--random: the seed of the draws (default 0)")
    ap.add_argument("--max-vertices", type=int, default=None, help="--random: largest mesh per object "
                    "(200: coarse meshes only)")
    ap.add_argument("--max-objects", type=int, default=3, help="--random: most objects per scene (1-3, default 3)")
    ap.add_argument("--steps", type=int, default=None, help="--random: steps of every target (default: the case's "
                    "duration / dt)")
    ap.add_argument("--dt", type=float, default=None, help="--random: dt of every target (default: per case, "
                    "below the stability bound)")
    ap.add_argument("--stop-after", type=float, default=1.0, help="--random: stop a fit after this many times its "
                    "time budget (default 1: at the budget; 0: never)")
    ap.add_argument("--in-process", action="store_true", help="--random: fit every case in this process "
                    "(default: each in a fresh process)")
    ap.add_argument("--no-linear-start", action="store_true", help="--random: fit without the linear start "
                    "(jaxplush-fit --no-linear-start), to compare")
    ap.add_argument("--polish", default=None, choices=("float64",), help="every fit with jaxplush-fit --polish "
                    "(its local stages again in float64 after the default fit), to compare")
    ap.add_argument("--oracle-only", action="store_true", help="--random: compute only the oracle of every case "
                    "(benchmarks/oracle.py: which parameters its target determines, at the truth), one JSON line "
                    "each (--json), before any fit runs")
    ap.add_argument("--oracle", default=None, metavar="FILE", help="--random: judge the fits against the oracle "
                    "lines of this draw in FILE (written by --oracle-only)")
    ap.add_argument("--only", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.no_linear_start:
        FIT_ARGS.append("--no-linear-start")
    if args.polish:
        FIT_ARGS.extend(["--polish", args.polish])
    if args.random is not None:
        if args.random < 1 or not 1 <= args.max_objects <= 3:
            ap.error("--random needs N >= 1 and --max-objects 1-3")
        return main_random(args)
    corners = list(itertools.product((0.5, 2.0), repeat=3))
    if args.corners != "all":
        picked = [int(c) for c in args.corners.split(",")]
        corners = corners[:picked[0]] if len(picked) == 1 else [corners[i] for i in picked]
    print(f"# {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}; "
          f"{time.strftime('%Y-%m-%d %H:%M')}" + (f"; --polish {args.polish}" if args.polish else ""), flush=True)
    print("| scene | target | start (k, damping, nmol) | wall s | exit | status | max error | errors |", flush=True)
    print("|---|---|---|---:|---:|---|---:|---|", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name in args.scenes.split(","):
            for kind in args.kinds.split(","):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    truth, target = make_case_files(d, name, kind)
                for factors in corners:
                    row = run_case(d, name, kind, truth, target, factors,
                                   extra=(*(() if args.jacobian is None else ("--jacobian", args.jacobian)),
                                          *FIT_ARGS))
                    rows.append(row)
                    errs = " ".join(f"{n.replace('k_structural', 'k')} {100 * e:+.3f}%" for n, e in row["errors"].items())
                    flag = "" if row.get("passed") else " **FAILED**"
                    print(f"| {name} | {kind} | x{factors[0]:g}, x{factors[1]:g}, x{factors[2]:g} | {row['wall']:.1f} | "
                          f"{row['exit']} | {row['status']}{flag} | {100 * row['max_error']:.3f}% | {errs} |", flush=True)
                    if args.json:
                        with open(args.json, "a") as fh:
                            fh.write(json.dumps(row) + "\n")
    passed = sum(bool(r.get("passed")) for r in rows)
    print(f"\n{passed} of {len(rows)} cases passed "
          f"(converged, within {100 * TOLERANCE['positions']:g}% / {100 * TOLERANCE['points']:g}%, in time)")
    for r in rows:
        if not r.get("passed"):
            print(f"FAILED: {r['scene']} {r['kind']} start x{r['factors']}: exit {r['exit']}, {r['status']}, "
                  f"max error {100 * r['max_error']:.3g}%, {r['wall']:.1f} s: {r.get('message', '')[:200]}")
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
