"""Run by tests/test_scale_out.py in a subprocess whose XLA_FLAGS force N host devices: a batched
contact rollout (padding, separations, a blown-up lane), the fit's Evaluator (its global stage,
the target's frames in one piece and in padded pieces) and a sweep with a target; every array
goes to one .npz for comparison across device counts.

Usage: python tests/sharding_worker.py OUT.npz
"""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

import jax                                    # noqa: E402
import jaxplush                               # noqa: E402
from jaxplush.stepping import batched          # noqa: E402
from test_batched_contact import DT, _pressed_problem, _thrown  # noqa: E402

def collect():
    """Every array of the three runs, by name."""
    res = {"devices": np.asarray(len(jax.local_devices()))}
    # 1. a contact rollout of 20 lanes (the last group padded), one lane blowing up
    scene, n, v0 = _thrown()
    k = np.linspace(120.0, 400.0, 20)
    k[7] = 5e6                                               # unstable at this dt
    bsim = batched.make_batched_simulator(scene, DT, 20)
    pb = bsim.params(scene.params._replace(k_structural=np.stack([k, k[::-1]])))
    final, frames, health, sep = batched.rollout(bsim, pb, bsim.init_fn(pb, None, v0), 8, 25,
                                                 observe=batched.positions_observer, separation=True)
    res.update(frames=np.asarray(frames), final=batched.positions(final), code=np.asarray(health.code),
               bad_step=np.asarray(health.bad_step), good=batched.positions(health.good_state),
               sep=np.asarray(sep))
    # 2. the fit's Evaluator on a pressed pair (the global stage's batched path)
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob = _pressed_problem()
    thetas = np.asarray(prob.theta0)[None] + np.linspace(-0.4, 0.4, 9)[:, None, None] * np.array([[[1.0, -0.5]]])
    e = Evaluator(prob, calibrate=False)(thetas, keep_frames=True)
    res.update(ev_loss=e.loss, ev_residuals=e.residuals, ev_ok=e.ok)
    # and in pieces of 3 of its 8 frames: one padded program for the pieces of 3 and of 2
    e = Evaluator(prob, calibrate=False, chunk_frames=3)(thetas, keep_frames=True)
    res.update(ev_pieces_loss=e.loss, ev_pieces_ok=e.ok)
    # 3. a sweep against a target
    from jaxplush.fitting.sweep import sweep
    from jaxplush.fitting.targets import make_target
    target = make_target(scene, 100, DT, 25)
    sw = sweep(scene, {"k": np.linspace(100, 300, 6), "nmol@b": [5e-4, 1e-3, 2e-3]}, steps=100, dt=DT,
               target=target, progress=False, batch=32)
    res.update(sweep_loss=sw.loss, sweep_final=sw.final_positions)
    return res


def main(out):
    calls = []
    real = batched._sharded_jit
    batched._sharded_jit = lambda *a, **k: calls.append(1) or real(*a, **k)
    res = collect()
    np.savez(out, sharded_calls=np.asarray(len(calls)), **res)


if __name__ == "__main__":
    main(sys.argv[1])
