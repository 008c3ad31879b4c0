"""jaxplush: differentiable pressurised mass-spring soft bodies ("plushies") in JAX.

Quick use (run from the repository root; the test suite executes this example):

>>> import jaxplush
>>> scene = jaxplush.load_scene("scenes/hanging.obj")
>>> traj = jaxplush.simulate(scene, steps=400, dt=5e-4, save_every=40)
>>> traj.positions.shape                      # (T, V, 3): frame 0 and one every 40 steps
(11, 162, 3)

Lower level: ``sim = make_simulator(scene, dt)``; ``params = sim.params()``;
``state = sim.init_fn(params)``; ``state = sim.step_fn(params, state)``;
``final, frames, health = rollout(sim, params, state, n_frames, save_every)``.

>>> sim = jaxplush.make_simulator(scene, 5e-4)
>>> params = sim.params()
>>> final, frames, health = jaxplush.rollout(sim, params, sim.init_fn(params), 10, 40)
>>> frames.shape, health.failed
((10, 162, 3), False)
"""

__version__ = "0.1.0"

from jaxplush import _xla
_xla.hoist_constants()           # topology as data (before jax is imported, which reads the option)
_xla.disable_ynn_fusion()        # before anything starts a backend: XLA reads XLA_FLAGS once

from jaxplush.errors import JaxplushError, JaxplushWarning, SceneError, SimulationError, TrajectoryError
from jaxplush.io.trajectory import load_trajectory, save_trajectory
from jaxplush.stepping.rollouts import Health, rollout
from jaxplush.scene.parse import Scene, load_scene, parse_scene
from jaxplush.stepping.predictability import Predictability, predictability
from jaxplush.stepping.simulation import Trajectory, contact_capacity_needed, simulate
from jaxplush.stepping.stability import estimate as estimate_stable_dt
from jaxplush.stepping.step import INTEGRATORS, Simulator, make_simulator
from jaxplush.types import Params, State

import os as _os

if _os.environ.get("JAXPLUSH_CACHE_DIR"):
    # set explicitly: every process that imports jaxplush shares the persistent compilation cache
    # (the command-line tools turn it on themselves, in the default directory when this is unset)
    from jaxplush.stepping.compiled import enable_persistent_cache as _enable_persistent_cache
    _enable_persistent_cache()

__all__ = [
    "Health", "INTEGRATORS", "JaxplushError", "JaxplushWarning", "Params", "Predictability", "Scene", "SceneError", "SimulationError",
    "Simulator", "State", "Trajectory", "TrajectoryError", "contact_capacity_needed", "estimate_stable_dt", "load_scene",
    "load_trajectory", "make_simulator", "parse_scene", "predictability", "rollout", "save_trajectory", "simulate",
]
