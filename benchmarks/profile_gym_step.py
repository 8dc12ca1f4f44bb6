"""Where a Gymnasium environment step's time goes, system by system.

    .venv/bin/python benchmarks/profile_gym_step.py [--steps 100] [--colon 0] [--floor]

The environment (capsule_drake/ColonNavigation-v0, default observations, random actions
from reset seed 0) is stepped `steps` times after 5 steps of warm-up, with the Python
callbacks of the systems that run in its loop (the compliant wall's foundation and its
compiled kernels, the magnet force, the EPM's path shaper, stage, guard and clearance
watch, the environment's contact statistics, the run guard) each wrapped in a timer. Printed
per callback: calls per environment step, microseconds per call and milliseconds per
environment step. The times are inclusive (a callback that evaluates another's output
includes it) and the timers add ~1 us a call; no cProfile, whose own cost per call is
larger than many of these callbacks. The line above the table: the environment steps per
CPU second of this process, timers included.

With --floor, instead: what the framework itself costs a plant step, with none of this
project's systems: a discrete MultibodyPlant (2 ms, SAP, hydroelastic with fallback) with one
free capsule-sized body, with and without two collision geometries, and the same with 1, 5
and 10 trivial Python systems updated every step (each call's dispatch from Drake into
Python). The environment's 50 plant steps a step have this floor whatever its systems do.
"""

import argparse
import collections
import functools
import time


def timed(timers, label, original):
    """`original`, its time and calls added to timers[label]."""
    @functools.wraps(original)
    def call(*args, **kwargs):
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            timers[label][0] += time.perf_counter() - start
            timers[label][1] += 1

    return call


def wrap(timers, cls, name, label=None):
    label = label or f"{cls.__name__.split('_')[0]}.{name}"
    setattr(cls, name, timed(timers, label, getattr(cls, name)))


def wrap_function(timers, module, name):
    setattr(module, name, timed(timers, f"kernel {name}", getattr(module, name)))


def instrument(timers):
    from capsule_drake.app import gym_parts
    from capsule_drake.epm import clearance, guard, shaping, stage
    from capsule_drake.io import guard as run_guard
    from capsule_drake.physics import magnet_force
    from capsule_drake.physics.contact import foundation, foundation_kernels

    for name in ("_calc_force", "_update", "_calc_wall_contact", "_geometry"):
        wrap(timers, foundation.FoundationContact, name)
    for name in ("contact_cells", "implicit_wrench", "next_bristles"):
        wrap_function(timers, foundation_kernels, name)
    # The magnet force's float instantiation (one class, under two names in the module).
    classes = {id(c): c for c in vars(magnet_force).values()
               if isinstance(c, type) and "_calc_magnet_values_float" in vars(c)}
    for cls in classes.values():
        for name in ("_calc_magnet_values_float", "_calc_implicit_torques",
                     "_update_implicit_state", "_calc_applied_spatial_force_implicit"):
            wrap(timers, cls, name, f"MagneticForce.{name}")
    for cls, names in ((shaping.EpmPathShaper, ("_update", "_calc_command")),
                       (stage.PoseToStage, ("_update",)), (stage.EpmFrame, ("_update",)),
                       (stage.KinematicStage, ("_calc_pose", "_calc_state")),
                       (guard.EpmCommandGuard, ("_update", "_calc_command")),
                       (clearance.EpmClearanceWatch, ("_check",)),
                       (gym_parts.ContactStats, ("_update",)),
                       (run_guard.RunGuard, ("_check_state", "_check_wall"))):
        for name in names:
            wrap(timers, cls, name)


def floor(seconds: float = 10.0):
    """Microseconds of CPU per plant step of bare plants (module docstring, --floor)."""
    from pydrake.geometry import Box, Capsule
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import (AddMultibodyPlant, CoulombFriction,
                                         MultibodyPlantConfig)
    from pydrake.multibody.tree import SpatialInertia
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder, LeafSystem

    step = 2e-3

    class Tick(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclareDiscreteState(1)
            self.DeclarePeriodicDiscreteUpdateEvent(step, 0.0, self._update)

        def _update(self, context, discrete_state):
            pass

    print(f"{'plant':<44}{'us per plant step':>18}")
    for geometry, ticks in ((False, 0), (True, 0), (True, 1), (True, 5), (True, 10)):
        builder = DiagramBuilder()
        plant, _ = AddMultibodyPlant(MultibodyPlantConfig(
            time_step=step, discrete_contact_approximation="lagged",
            contact_model="hydroelastic_with_fallback"), builder)
        body = plant.AddRigidBody("capsule", SpatialInertia.SolidCylinderWithMass(
            0.012, 0.0055, 0.031, [0.0, 0.0, 1.0]))
        if geometry:
            friction = CoulombFriction(0.3, 0.3)
            plant.RegisterCollisionGeometry(body, RigidTransform(), Capsule(0.0055, 0.02),
                                            "capsule", friction)
            plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0, 0, 1.0]),
                                            Box(0.01, 0.01, 0.01), "box", friction)
        plant.Finalize()
        for _ in range(ticks):
            builder.AddSystem(Tick())
        simulator = Simulator(builder.Build())
        simulator.Initialize()
        cpu = time.process_time()
        simulator.AdvanceTo(seconds)
        cpu = time.process_time() - cpu
        label = ("one free body" + (", two geometries" if geometry else "")
                 + (f", {ticks} Python system{'s' if ticks > 1 else ''}" if ticks else ""))
        print(f"{label:<44}{1e6 * cpu / round(seconds / step):>18.1f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--colon", type=int, default=0)
    parser.add_argument("--floor", action="store_true",
                        help="the framework's own cost a plant step (module docstring)")
    args = parser.parse_args()
    if args.floor:
        floor()
        return
    timers = collections.defaultdict(lambda: [0.0, 0])
    instrument(timers)
    import gymnasium

    import capsule_drake  # noqa: F401  (registers the environment)
    from capsule_drake.app.gym_env import ENV_ID

    env = gymnasium.make(f"capsule_drake:{ENV_ID}", colons=(args.colon,))
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(5):
        env.step(env.action_space.sample())
    timers.clear()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(args.steps):
        env.step(env.action_space.sample())
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"{args.steps} steps: {args.steps / cpu:.1f} steps per CPU second, "
          f"{1000 * wall / args.steps:.1f} ms a step (wall)")
    print(f"{'callback':<46}{'calls/step':>11}{'us/call':>10}{'ms/step':>10}")
    for label, (seconds, calls) in sorted(timers.items(), key=lambda kv: -kv[1][0]):
        print(f"{label:<46}{calls / args.steps:>11.1f}{1e6 * seconds / calls:>10.1f}"
              f"{1000 * seconds / args.steps:>10.2f}")
    env.close()


if __name__ == "__main__":
    main()
