"""Dipole against finite-size magnets: accuracy against distance, and cost per step.

Prints, for the Navigation scenario's magnets (N52 cylinders 101.6 mm and 11.1 mm), at
8-25 cm centre distance:
  - the force and torque errors of the point dipole and of the finite model
    (`MagneticForce` field_model "finite") against magpylib's meshed reference
    (`magpylib.getFT`, the capsule's magnet cut into 24 x 8 x 12 cells), coaxial and over
    random poses (median and 95th percentile);
  - the median cost of one MagneticForce evaluation (the cache invalidated by a change of
    the capsule's pose, as in each 1 ms physics step) with each model;
and writes the error plot (default docs/dipole_vs_finite.png).

Run: python benchmarks/bench_magnet_model.py [--poses 40] [--plot PATH]
"""

import argparse

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec
from capsule_drake.physics.magnetics import (cylinder_moment, cylinder_pair_interaction_float,
                                             dipole_pair_interaction_float,
                                             meshed_reference_wrench)
from timing import median_us  # benchmarks/timing.py

D, L, BR = 0.1016, 0.1016, 1.48
d, l = 0.0111, 0.0111
M_EPM, M_IPM = cylinder_moment(D, L, BR), cylinder_moment(d, l, BR)
DISTANCES = [0.08, 0.09, 0.10, 0.12, 0.15, 0.20, 0.25]


def errors(a, c, p):
    F, T = meshed_reference_wrench(M_EPM * a, M_IPM * c, p, (D, L), (d, l))
    out = []
    for r in (dipole_pair_interaction_float(M_EPM * a, M_IPM * c, p),
              cylinder_pair_interaction_float(M_EPM * a, M_IPM * c, p, D, L,
                                              target_size=(d, l))):
        out.append((np.linalg.norm(np.array(r.force_target) - F) / np.linalg.norm(F),
                    np.linalg.norm(np.array(r.torque_target) - T) / np.linalg.norm(T)))
    return out  # [(dipole F, dipole T), (finite F, finite T)]


def accuracy(poses: int, seed: int = 0):
    rng = np.random.default_rng(seed)

    def unit():
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    table = {}
    for distance in DISTANCES:
        z = np.array([0.0, 0.0, 1.0])
        coaxial = errors(z, z, distance * z)
        # Coaxial torque is zero: only its force is reported.
        sampled = np.array([errors(unit(), unit(), distance * unit()) for _ in range(poses)])
        table[distance] = (coaxial, sampled)
        print(f"{100 * distance:4.0f} cm | coaxial F: dipole {100 * coaxial[0][0]:6.2f} %,"
              f" finite {100 * coaxial[1][0]:6.3f} % | random F median/95th: dipole"
              f" {100 * np.median(sampled[:, 0, 0]):6.2f}/"
              f"{100 * np.percentile(sampled[:, 0, 0], 95):6.2f} %, finite"
              f" {100 * np.median(sampled[:, 1, 0]):6.3f}/"
              f"{100 * np.percentile(sampled[:, 1, 0], 95):6.3f} % | random T median/95th:"
              f" dipole {100 * np.median(sampled[:, 0, 1]):6.2f}/"
              f"{100 * np.percentile(sampled[:, 0, 1], 95):6.2f} %, finite"
              f" {100 * np.median(sampled[:, 1, 1]):6.3f}/"
              f"{100 * np.percentile(sampled[:, 1, 1], 95):6.3f} %", flush=True)
    return table


def plot(table, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = 100 * np.array(DISTANCES)
    fig, (ax_f, ax_t) = plt.subplots(1, 2, figsize=(10, 4))
    for k, (name, colour) in enumerate((("point dipole", "tab:red"),
                                        ("finite (exact cylinder)", "tab:blue"))):
        med_f = [100 * np.median(table[dist][1][:, k, 0]) for dist in DISTANCES]
        p95_f = [100 * np.percentile(table[dist][1][:, k, 0], 95) for dist in DISTANCES]
        med_t = [100 * np.median(table[dist][1][:, k, 1]) for dist in DISTANCES]
        p95_t = [100 * np.percentile(table[dist][1][:, k, 1], 95) for dist in DISTANCES]
        ax_f.plot(x, med_f, "o-", color=colour, label=f"{name}, median")
        ax_f.plot(x, p95_f, "o--", color=colour, alpha=0.6, label=f"{name}, 95th pct.")
        ax_t.plot(x, med_t, "o-", color=colour, label=f"{name}, median")
        ax_t.plot(x, p95_t, "o--", color=colour, alpha=0.6, label=f"{name}, 95th pct.")
    coax = [100 * table[dist][0][0][0] for dist in DISTANCES]
    ax_f.plot(x, coax, "s:", color="tab:red", label="point dipole, coaxial")
    for ax, what in ((ax_f, "force"), (ax_t, "torque")):
        ax.set_yscale("log")
        ax.axhline(1.0, color="grey", lw=0.8)
        ax.set_xlabel("centre distance EPM - capsule magnet (cm)")
        ax.set_ylabel(f"{what} error vs meshed reference (%)")
        ax.grid(alpha=0.3, which="both")
    ax_f.set_title("force on the capsule's magnet")
    ax_t.set_title("torque on the capsule's magnet")
    ax_f.legend(fontsize=7)
    fig.suptitle("N52 cylinders 101.6 mm (EPM) and 11.1 mm (capsule); reference: magpylib getFT")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def step_cost():
    """Median microseconds of one MagneticForce evaluation after a pose change."""
    out = {}
    for model in ("dipole", "finite"):
        builder = DiagramBuilder()
        plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
        capsule = plant.AddRigidBody(
            "capsule", SpatialInertia.SolidCylinderWithMass(0.012, 0.0055, 0.026, [0, 0, 1]))
        epm = plant.AddRigidBody(
            "epm", SpatialInertia.SolidCylinderWithMass(6.2, 0.0508, 0.1016, [0, 0, 1]))
        plant.WeldFrames(plant.world_frame(), epm.body_frame(), RigidTransform([0, 0, 0.2]))
        plant.Finalize()
        magnetic = builder.AddSystem(MagneticForce(plant, [
            MagnetSpec(name="ipm", body="capsule", p_BM=[0, 0, -0.003], moment=M_IPM,
                       cylinder=[d, l]),
            MagnetSpec(name="epm", body="epm", moment=M_EPM, cylinder=[D, L])],
            field_model=model))
        builder.Connect(plant.get_body_poses_output_port(),
                        magnetic.get_body_poses_input_port())
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        plant_context = plant.GetMyContextFromRoot(context)
        mf_context = magnetic.GetMyContextFromRoot(context)
        port = magnetic.get_applied_spatial_force_output_port()
        poses = [RigidTransform(RollPitchYaw(0.1 * k, 0.2, 0.0), [0.01 * k, 0.0, 0.0])
                 for k in range(2)]
        flip = [0]

        def kinematics_only():
            flip[0] ^= 1
            plant.SetFreeBodyPose(plant_context, capsule, poses[flip[0]])
            plant.get_body_poses_output_port().Eval(plant_context)

        def evaluate():
            kinematics_only()
            port.Eval(mf_context)

        out[model] = median_us(evaluate, number=500) - median_us(kinematics_only, number=500)
        print(f"MagneticForce, {model:6s}: {out[model]:7.1f} us per evaluation "
              f"(the plant's pose kinematics subtracted)", flush=True)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=40, help="random poses per distance")
    parser.add_argument("--plot", default="docs/dipole_vs_finite.png")
    parser.add_argument("--cost-only", action="store_true")
    args = parser.parse_args()
    step_cost()
    if not args.cost_only:
        plot(accuracy(args.poses), args.plot)


if __name__ == "__main__":
    main()
