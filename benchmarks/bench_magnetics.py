"""Cost of the point-dipole magnetics and of the MagneticForce system.

Prints the median microseconds per call of:
  - force + torque with the generic functions (float and AutoDiffXd),
  - the float fast path used by MagneticForce at 1 kHz,
  - a MagneticForce output evaluation inside a plant diagram (cache invalidated by
    a change of the plant positions; the plant's own pose kinematics is timed
    separately and subtracted),
  - one 1 ms simulator step with and without the magnets,
  - the default station's 1 ms step (``--station``): as built, with the magnet moments
    set to zero (same Python work, no magnetic physics), and with MagneticForce's
    output not applied (scenario ``magnet_force: {apply: false}``). The last two
    follow identical trajectories, so their difference is what MagneticForce costs
    inside the simulation. The simulators advance in interleaved 50 ms chunks and chunk
    times are compared pairwise, so load from other processes mostly cancels.

Run: python benchmarks/bench_magnetics.py [--station [--sim-seconds 3]]
"""

import argparse
import contextlib
import dataclasses
import random
import statistics
import time

import numpy as np
from pydrake.autodiffutils import InitializeAutoDiff
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec
from capsule_drake.physics.magnetics import (
    dipole_force,
    dipole_pair_interaction,
    dipole_pair_interaction_float,
    dipole_pair_wrench,
    dipole_torque,
)
from timing import median_us  # benchmarks/timing.py

# Only for --station (imports the colon builder).
STATION_VARIANTS = ("as built", "zero moments", "no MagneticForce")


def build_diagram(with_magnets):
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
    capsule = plant.AddRigidBody(
        "capsule", SpatialInertia.SolidCylinderWithMass(0.005, 0.0055, 0.026, [0, 0, 1])
    )
    epm = plant.AddRigidBody(
        "epm", SpatialInertia.SolidCylinderWithMass(6.2, 0.0508, 0.1016, [0, 0, 1])
    )
    plant.WeldFrames(plant.world_frame(), epm.body_frame(), RigidTransform([0, 0, 0.5]))
    plant.Finalize()
    magnetic = None
    if with_magnets:
        magnetic = builder.AddSystem(
            MagneticForce(
                plant,
                [
                    MagnetSpec(name="ipm", body="capsule", p_BM=[0, 0, 0.005], moment=1.26),
                    MagnetSpec(name="epm", body="epm", moment=970.0),
                ],
            )
        )
        builder.Connect(
            plant.get_body_poses_output_port(), magnetic.get_body_poses_input_port()
        )
        builder.Connect(
            magnetic.get_applied_spatial_force_output_port(),
            plant.get_applied_spatial_force_input_port(),
        )
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant.SetFreeBodyPose(
        plant.GetMyContextFromRoot(context),
        capsule,
        RigidTransform(RollPitchYaw(0.3, 0.2, 0.1), [0.01, 0.02, 0.0]),
    )
    return diagram, plant, magnetic, context


@contextlib.contextmanager
def _patched(module, name, value):
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


def build_station(variant):
    """The default station, or a variant of it: its magnet force block patched to zero
    moments, or the scenario's ``magnet_force: {apply: false}``."""
    from capsule_drake.physics import magnet_force
    from capsule_drake.scenario import load_scenario
    from capsule_drake.station import make_station

    if variant == "as built":
        return make_station(load_scenario())
    if variant == "zero moments":
        def zero_moment_force(plant, magnets, **kwargs):
            return MagneticForce(
                plant, [dataclasses.replace(m, moment=0.0) for m in magnets], **kwargs
            )

        # add_magnet_force (physics/magnet_force.py) builds the system by this name.
        with _patched(magnet_force, "MagneticForce", zero_moment_force):
            return make_station(load_scenario())
    assert variant == "no MagneticForce"
    return make_station(load_scenario(override="magnet_force: {apply: false}"))


def station_steps(sim_seconds, chunk=0.05, seed=0):
    """Per-step CPU time of each station variant, in interleaved chunks."""
    rng = random.Random(seed)
    simulators = {}
    for variant in STATION_VARIANTS:
        simulators[variant] = Simulator(build_station(variant))
        simulators[variant].Initialize()
    per_step = {variant: [] for variant in STATION_VARIANTS}
    for k in range(int(round(sim_seconds / chunk))):
        order = list(STATION_VARIANTS)
        rng.shuffle(order)  # no variant always runs right after another
        for variant in order:
            start = time.process_time()
            simulators[variant].AdvanceTo((k + 1) * chunk)
            # CPU seconds per simulated second = ms per 1 ms step.
            per_step[variant].append((time.process_time() - start) / chunk)
    baseline = per_step["no MagneticForce"]
    print(f"\ndefault station, {sim_seconds:g} s in {chunk * 1e3:g} ms chunks "
          "(CPU time, median over chunks)")
    print(f"{'us per 1 ms step':>20}  {'RTF':>5}  {'minus no-magnet':>15}  variant")
    for variant, times in per_step.items():
        extra = statistics.median(t - b for t, b in zip(times, baseline))
        step = statistics.median(times)
        print(f"{step * 1e3:20.1f}  {1.0 / step:5.2f}  {extra * 1e3:15.1f}  {variant}")
    print("(zero moments minus no-magnet = MagneticForce's cost per step in the "
          "simulation; as built also differs in physics: the capsule is dragged)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--number", type=int, default=2000)
    parser.add_argument("--station", action="store_true",
                        help="also time the default station's step (builds the colon)")
    parser.add_argument("--sim-seconds", type=float, default=3.0,
                        help="simulated seconds per station variant")
    args = parser.parse_args()
    R, N = args.repeats, args.number

    m_s = 970.0 * np.array([0.0, 0.3, 0.95])
    m_t = 1.26 * np.array([1.0, 0.0, 0.0])
    p = np.array([0.02, -0.03, 0.14])
    p_ad = InitializeAutoDiff(p).reshape(3)
    m_s_tuple, m_t_tuple, p_tuple = tuple(m_s.tolist()), tuple(m_t.tolist()), tuple(p.tolist())
    p_ad14 = InitializeAutoDiff(p, 14).reshape(3)

    rows = [
        ("generic float: dipole_force + dipole_torque",
         lambda: (dipole_force(m_s, m_t, p), dipole_torque(m_s, m_t, p)), N),
        ("generic float: dipole_pair_wrench", lambda: dipole_pair_wrench(m_s, m_t, p), N),
        ("generic float: dipole_pair_interaction (2 fields + wrenches)",
         lambda: dipole_pair_interaction(m_s, m_t, p), N),
        ("fast float: dipole_pair_interaction_float (tuples in and out)",
         lambda: dipole_pair_interaction_float(m_s_tuple, m_t_tuple, p_tuple), N),
        ("AutoDiffXd (3 derivs): dipole_force + dipole_torque",
         lambda: (dipole_force(m_s, m_t, p_ad), dipole_torque(m_s, m_t, p_ad)), N // 10),
        ("AutoDiffXd (14 derivs): dipole_pair_interaction",
         lambda: dipole_pair_interaction(m_s, m_t, p_ad14), N // 10),
    ]
    print(f"{'median us per call':>20}  what")
    for label, fn, number in rows:
        print(f"{median_us(fn, R, number):20.2f}  {label}")

    # MagneticForce inside a diagram: perturb q so that every cache is invalid.
    diagram, plant, magnetic, context = build_diagram(with_magnets=True)
    plant_context = plant.GetMyContextFromRoot(context)
    mf_context = magnetic.GetMyContextFromRoot(context)
    q = plant.GetPositions(plant_context)
    dq = np.zeros_like(q)
    dq[-1] = 1e-9
    state = {"sign": 1.0}

    def touch():
        state["sign"] = -state["sign"]
        plant.SetPositions(plant_context, q + state["sign"] * dq)

    def poses_only():
        touch()
        plant.get_body_poses_output_port().Eval(plant_context)

    def force_output():
        touch()
        magnetic.get_applied_spatial_force_output_port().Eval(mf_context)

    def all_outputs():
        touch()
        magnetic.get_applied_spatial_force_output_port().Eval(mf_context)
        for name in magnetic.magnet_names():
            magnetic.get_B_B_output_port(name).Eval(mf_context)
            magnetic.get_F_W_output_port(name).Eval(mf_context)

    t_poses = median_us(poses_only, R, N)
    t_force = median_us(force_output, R, N)
    t_all = median_us(all_outputs, R, N)
    print(f"{t_poses:20.2f}  diagram: SetPositions + body_poses (baseline)")
    print(f"{t_force:20.2f}  diagram: + MagneticForce applied_spatial_force "
          f"(magnet share {t_force - t_poses:.2f})")
    print(f"{t_all:20.2f}  diagram: + all MagneticForce outputs "
          f"(magnet share {t_all - t_poses:.2f})")

    # One 1 ms plant step with and without the magnet system.
    for with_magnets in (False, True):
        diagram, plant, magnetic, context = build_diagram(with_magnets)
        simulator = Simulator(diagram, context)
        simulator.Initialize()
        steps = 500
        start = time.perf_counter()
        simulator.AdvanceTo(steps * 1e-3)
        per_step = (time.perf_counter() - start) / steps * 1e6
        label = "with" if with_magnets else "without"
        print(f"{per_step:20.2f}  simulator step (1 ms, free capsule, welded EPM) {label} magnets")

    if args.station:
        station_steps(args.sim_seconds)


if __name__ == "__main__":
    main()
