"""Multi-object fits: the full-dimensional global stage against the per-object one.

Cases (``jaxplush.fitting.targets.scenarios`` placement, the report's per-step damping 2000 on every
object, a floor at y = 0, soft-soft contact on):

* ``two``: two 162-vertex balls (0.12 kg), the lower one 5 cm above the floor, the upper one
  dropped from 4 cm above it (shifted 1 cm sideways), so that it lands on the lower one;
* ``three``: a 162-vertex ball, a 162-vertex cushion and a 162-vertex ball stacked the same way.

Each object has its own k_structural and gas (nmol from its rest pressure); the fit frees k and
nmol of every object, from starts alternately x2 / x0.5 (object 0: k x2, nmol x0.5; object 1:
k x0.5, nmol x2; ...). Targets: noise-free positions, simulated with the scene (``--steps``
steps of ``--dt``, about 40 frames). Each variant runs, in a fresh process (import and compile
included; the persistent compilation cache as ``--cache`` says), the default fit's continuation
in time (:class:`jaxplush.fitting.stages.Continuation`: the first stage and Levenberg-Marquardt
on the first quarter of the frames, then a half, then all) through ``stages.run_stages`` with
the default fit's options, the first stage being:

* ``global``: :class:`jaxplush.fitting.stages.GlobalStage` (64 Sobol points, 5 starts), as the default fit;
* ``objects``: :class:`jaxplush.fitting.stages.objects.PerObjectGlobal` (``--rounds`` rounds of 64
  points and the combinations of each object's best 3 blocks);
* ``fit``: ``jaxplush.fitting.fit`` with its defaults, as a user runs it (the predictability
  measurement, the shooting plan, the per-object stage, which it picks for several objects, the
  continuation, and the linearisation at the best point for the outcome); ``stop`` is its status.

It prints a table: wall time, loss, the stop of the best search, and the relative error of every
parameter. Acceptance (issue 25): two balls within 60 s, three objects within 180 s, every
parameter within 1%.

Usage: python benchmarks/bench_multi_object.py [--cases two,three] [--variants global,objects]
           [--rounds 3] [--cache off|DIR] [--json out.jsonl]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

CASES = {"two": ("ball", "ball"), "three": ("ball", "cushion", "ball")}
K = (420.0, 300.0, 550.0)
PRESSURE = (1800.0, 2400.0, 1500.0)
DT, STEPS, EVERY = 5e-4, 800, 20


def case_dict(shapes, level=2):
    """A ``scenarios`` case of objects stacked on a floor (see the module docstring)."""
    from jaxplush.fitting.targets import scenarios as S
    objs = []
    for i, shape in enumerate(shapes):
        objs.append(dict(name=f"{shape}{i}", shape=shape, level=level, vertices=S.mesh_vertices(shape, level),
                         k_structural=K[i], total_weight=0.12, pressure=PRESSURE[i], damping=2000.0,
                         tilt_deg=0.0, yaw_deg=0.0, position=[0.0, 0.0, 0.0]))
    below = None
    for i, o in enumerate(objs):
        v, _ = S._placed(o)
        lo = v.min(0)
        base = 0.05 if below is None else below + 0.04
        o["position"] = [0.01 * i, base - lo[1], -0.01 * i]
        below = float(S._placed(o)[0][:, 1].max())
    return dict(setting="floor", n_objects=len(objs), damping_model="damping", kind="positions",
                floor_friction=None, objects=objs, params=["k_structural", "nmol"], start={}, duration=STEPS * DT,
                contact_capacity=None)


def start_factors(n):
    return {"k_structural": [2.0 if i % 2 == 0 else 0.5 for i in range(n)],
            "nmol": [0.5 if i % 2 == 0 else 2.0 for i in range(n)]}


def run_one(case_name, variant, rounds):
    """One fit in this process; returns the table's row (dict)."""
    import warnings
    import jaxplush
    from jaxplush.fitting import fitter as F, stages
    from jaxplush.fitting.stages import lmfit, objects
    from jaxplush.fitting.targets import scenarios as S
    from jaxplush.fitting.options import FitOptions
    from jaxplush.fitting.targets import make_target
    warnings.simplefilter("ignore")
    case = case_dict(CASES[case_name])
    truth = jaxplush.parse_scene(S.case_scene_text(case), "<truth>")
    cap = jaxplush.contact_capacity_needed(truth, STEPS, DT)
    if cap:
        case["contact_capacity"] = int(cap)
        truth = jaxplush.parse_scene(S.case_scene_text(case), "<truth>")
    target = make_target(truth, STEPS, DT, EVERY)
    scene = jaxplush.parse_scene(S.case_scene_text(case, start_factors(len(case["objects"]))), "<start>")
    t0 = time.perf_counter()
    if variant == "fit":
        res = F.fit(scene, target, ("k_structural", "nmol"), noise_free=True)
        wall = time.perf_counter() - t0
        got = np.log(np.stack([res.values["k_structural"], res.values["nmol"]]))
        true = np.log(np.stack([truth.params.k_structural, truth.params.nmol]))
        rel = np.exp(got - true) - 1.0
        return dict(case=case_name, variant=variant, rounds=None, wall=wall, loss=float(res.loss), stop=res.status,
                    reason=res.reason, evaluations=int(res.iterations), labels=list(res.problem.labels),
                    rel_error=rel.ravel().tolist(), max_error=float(np.max(np.abs(rel))))
    prob = F.build_problem(scene, target, ("k_structural", "nmol"), noise_free=True)
    opts = FitOptions()
    box = lmfit.default_box(prob)
    if variant == "global":
        first = stages.GlobalStage(samples=opts.search.n_samples, starts=opts.search.n_starts, local=opts.local)
    else:
        first = objects.PerObjectGlobal(samples=opts.search.n_samples, rounds=rounds, starts=opts.search.n_starts,
                                        local=opts.local)
    local = stages.LocalLM(max_iter=opts.iteration_limit("lm"), options=opts.local)
    cont = stages.Continuation(local=local, first=(first,), options=opts.continuation)
    objective = stages.Objective(prob, box)
    (state,) = stages.run_stages(objective, prob.theta0, [cont])
    wall = time.perf_counter() - t0
    best = state.states[stages.order(state.states)[0]]
    true = np.log(np.stack([truth.params.k_structural, truth.params.nmol]))
    rel = np.exp(best.theta - true) - 1.0
    return dict(case=case_name, variant=variant, rounds=rounds if variant == "objects" else None,
                wall=wall, loss=float(best.loss), stop=best.stopped.name, reason=best.reason,
                evaluations=int(state.horizons.evaluations()), labels=list(prob.labels),
                rel_error=rel.ravel().tolist(), max_error=float(np.max(np.abs(rel))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="two,three")
    ap.add_argument("--variants", default="global,objects")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the per-object stage")
    ap.add_argument("--cache", default="off", help="persistent compilation cache: off, or a directory")
    ap.add_argument("--json", default=None)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)     # CASE:VARIANT, run here
    args = ap.parse_args(argv)
    if args.one:
        case, variant = args.one.split(":")
        print(json.dumps(run_one(case, variant, args.rounds)))
        return 0
    env = dict(os.environ, JAXPLUSH_CACHE_DIR=args.cache)
    rows = []
    print("| case | first stage | wall s | evaluations | loss | stop | max error | errors (relative) |")
    print("|---|---|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        for variant in args.variants.split(","):
            out = subprocess.run([sys.executable, __file__, "--one", f"{case}:{variant}", "--rounds", str(args.rounds)],
                                 env=env, capture_output=True, text=True)
            lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
            if out.returncode or not lines:
                print(f"| {case} | {variant} | failed ({out.returncode}) | | | | | {out.stderr[-300:]!r} |")
                continue
            r = json.loads(lines[-1])
            rows.append(r)
            errs = " ".join(f"{lab} {e:+.2%}" for lab, e in zip(r["labels"], r["rel_error"]))
            name = variant if r["rounds"] is None else f"{variant} ({r['rounds']} rounds)"
            print(f"| {case} | {name} | {r['wall']:.1f} | {r['evaluations']} | {r['loss']:.3g} | {r['stop']} | "
                  f"{r['max_error']:.2%} | {errs} |", flush=True)
    if args.json:
        with open(args.json, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
