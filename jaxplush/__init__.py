"""jaxplush: differentiable pressurised mass-spring soft bodies ("plushies") in JAX.

Quick use::

    scene = jaxplush.load_scene("scenes/ball_drop.obj")
    traj = jaxplush.simulate(scene, steps=4000, dt=2.5e-4, save_every=40)
    traj.positions  # (T, V, 3)

Lower level: ``sim = make_simulator(scene, dt)``; ``params = sim.params()``;
``state = sim.init_fn(params)``; ``state = sim.step_fn(params, state)``;
``final, frames, health = rollout(sim, params, state, n_frames, save_every)``.
"""

__version__ = "0.1.0"

from jaxplush.errors import JaxplushError, SceneError, SimulationError, TrajectoryError
from jaxplush.io import load_trajectory, save_trajectory
from jaxplush.rollouts import Health, rollout
from jaxplush.scene import Scene, load_scene, parse_scene
from jaxplush.simulate import Trajectory, simulate
from jaxplush.stability import estimate as estimate_stable_dt
from jaxplush.step import INTEGRATORS, Simulator, make_simulator
from jaxplush.types import Params, State

__all__ = [
    "Health", "INTEGRATORS", "JaxplushError", "Params", "Scene", "SceneError", "SimulationError",
    "Simulator", "State", "Trajectory", "TrajectoryError", "estimate_stable_dt", "load_scene",
    "load_trajectory", "make_simulator", "parse_scene", "rollout", "save_trajectory", "simulate",
]
