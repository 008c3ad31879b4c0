"""Probes of a random case's reproducibility floor (issue 53): how sensitive its motion is, and how
the twins' intervals of a fit at the floor depend on the Jacobian's difference step.

    python benchmarks/floor_probe.py split --seed 1301 --index 6
    python benchmarks/floor_probe.py twins --seed 1101 --index 9 --kinds points --fit DIR/FIT.h5

``split``: the truth's frames against the same with drag's share of the damping+drag rate moved by
1e-6, 1e-4 and 1e-2 (the rate kept), and with k moved by 1e-4 and 1e-3: the RMS distance per
vertex of every fourth frame, mm. ``twins``: the fit's 95%-interval spreads
(:func:`jaxplush.fitting.judge.intervals.twins`, the pair damping/drag left out) at its values
(FIT.h5) with central-difference Jacobians at steps 1e-3, 1e-2 and 5e-2 (log space), each
parameter's error against the truth in spreads. Prints a table; writes nothing but the case's
files (in a temporary folder).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def case_files(d, seed, index, kinds):
    import bench_recovery as b
    case = b.draw_cases(index + 1, seed, max_vertices=None, max_objects=3, kinds=tuple(kinds.split(",")))[index]
    truth, target, start = b.random_case_files(d, case)
    return case, truth, target, start


def split(truth, case):
    import jaxplush
    dt, steps, every = case["dt"], case["steps"], case["save_every"]
    p = truth.params

    def frames(**kw):
        return np.asarray(jaxplush.simulate(truth.replace(params=p._replace(**kw)), steps=steps, dt=dt,
                                            save_every=every).positions, np.float64)

    ref = frames()
    rows = []
    if float(p.drag[0]) > 0 and float(p.damping[0]) > 0:
        rate = p.drag + 1.0 / (p.damping * dt)
        s0 = p.drag / rate
        for rel in (1e-6, 1e-4, 1e-2):
            s = s0 * (1 + rel)
            rows.append((f"drag's share x(1+{rel:g}), rate kept", frames(drag=s * rate, damping=1.0 / ((1 - s) * rate * dt))))
    for rel in (1e-4, 1e-3):
        rows.append((f"k x(1+{rel:g})", frames(k_structural=p.k_structural * (1 + rel))))
    print(f"| change | RMS distance per vertex from the truth's frames, every 4th frame of {len(ref)}, mm |")
    print("|---|---|")
    for what, f in rows:
        d = np.sqrt(((f - ref) ** 2).sum(-1).mean(-1))
        print(f"| {what} | {' '.join(f'{1e3 * x:.3g}' for x in d[::4])} |")


def twins(d, tag, truth, fit_path):
    import h5py
    import jaxplush
    from jaxplush import fitting as F
    from jaxplush.fitting.judge import intervals as I
    from jaxplush.fitting.objective.evaluate import Evaluator
    from jaxplush.fitting.objective.problem import build_problem
    from jaxplush.fitting.stages import search as S
    scene = jaxplush.load_scene(os.path.join(d, f"{tag}_start.obj"))
    prob = build_problem(scene, F.load_target(os.path.join(d, f"{tag}_target.h5"), scene))
    with h5py.File(fit_path) as f:
        theta = np.asarray(f["intervals/theta"][()]).reshape(np.shape(prob.theta0))
        sd_fit = np.asarray(f["intervals/sd"][()])
    ev = Evaluator(prob)
    box = S.Box(lo=np.minimum(prob.theta0, theta) - 3.0, hi=np.maximum(prob.theta0, theta) + 3.0)
    truth_th = np.log(np.stack([np.asarray(getattr(truth.params, n), np.float64)[list(prob.objects)]
                                for n in prob.names]))
    err = (theta - truth_th).ravel()
    r0 = ev(theta[None]).residuals[0]
    pair = "damping" in prob.names and "drag" in prob.names
    det = np.array([not (pair and lab.startswith(("damping[", "drag["))) for lab in prob.labels])
    report = type("Report", (), dict(determined=det, stderr=np.where(det, 1.0, np.inf), labels=tuple(prob.labels)))()
    cols = {}
    for h in (1e-3, 1e-2, 5e-2):
        iv = I.twins(prob, ev, theta, S.jacobian(ev, box, theta, h), report, residual=r0)
        cols[h] = iv.sd
    print("| parameter | error | FIT.h5 spread | " + " | ".join(f"spread, step {h:g} (error / spread)" for h in cols) + " |")
    print("|---|---:|---:|" + "---:|" * len(cols))
    for i, lab in enumerate(prob.labels):
        if not det[i]:
            continue
        print(f"| {lab} | {100 * err[i]:+.3g}% | {100 * sd_fit[i]:.3g}% | "
              + " | ".join(f"{100 * cols[h][i]:.3g}% ({abs(err[i]) / cols[h][i]:.3g})" for h in cols) + " |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("probe", choices=("split", "twins"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--index", type=int, required=True)
    ap.add_argument("--kinds", default="positions,points", help="the draw's --kinds (it changes the draw)")
    ap.add_argument("--fit", default=None, help="twins: the case's FIT.h5")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as d:
        case, truth, target, start = case_files(d, args.seed, args.index, args.kinds)
        print(f"# seed {args.seed} case {args.index}: dt {case['dt']:g} x {case['steps']} steps, a frame every "
              f"{case['save_every']}")
        if args.probe == "split":
            split(truth, case)
        else:
            if not args.fit:
                ap.error("twins needs --fit FIT.h5")
            twins(d, f"case{args.index:03d}", truth, args.fit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
