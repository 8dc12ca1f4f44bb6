"""Cost of the capsule's inertial and magnetic sensors, and the IMU's Allan deviation.

Prints:
  - median microseconds per call of the pure functions (noise sample, Mahony step, field
    at the sensor) and per sample of the vectorised recording;
  - microseconds each sensor system adds per update inside a simulation: a free capsule
    body in a 1 ms discrete plant (as in the station) is simulated with and without the
    sensor, in interleaved chunks; the extra time divided by the number of sensor updates
    is the figure. "Imu" includes Drake's Accelerometer and Gyroscope, the three
    RandomSources and ImuNoise;
  - the Allan deviation figures of a static MPU-6050 recording (ImuConfig defaults) against
    the configured densities, and optionally a PNG of the Allan plot (``--plot out.png``).

Run: python benchmarks/bench_imu.py [--sim-seconds 5] [--plot allan.png]
"""

import argparse
import math
import statistics
import time

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.capsule.ahrs import AhrsConfig, MahonyAhrs, mahony_update
from capsule_drake.capsule.allan import allan_deviation, white_noise_coefficient
from capsule_drake.capsule.imu import Imu, ImuConfig, add_random_sources, imu_channels
from capsule_drake.capsule.magnetometer import (
    Magnetometer,
    MagnetometerConfig,
    field_in_sensor_frame,
)
from capsule_drake.physics.magnet_force import MagnetSpec
from timing import median_us  # benchmarks/timing.py

VARIANTS = ("plant only", "+ Imu", "+ Imu + MahonyAhrs", "+ Magnetometer")


def pure_function_costs():
    config = ImuConfig()
    accel, gyro = imu_channels(config)
    truth, bias, draw = np.array([0.1, 0.2, 9.8]), np.zeros(3), np.ones(3)
    print("pure functions (us per call):")
    q, b = (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    a, w = (0.1, 0.2, 9.8), (0.01, 0.02, 0.3)
    X_WS = RigidTransform(RollPitchYaw(0.1, 0.2, 0.3), [0.0, 0.0, 0.0])
    sources = [(np.array([0.0, 0.05, 0.15]), np.array([0.0, 0.0, 970.0]))]
    for label, fn in (
            ("ChannelNoise.sample (one 3-axis sample)", lambda: accel.sample(truth, bias, draw)),
            ("mahony_update", lambda: mahony_update(q, b, a, w, 0.01, 1.0, 0.25, 0.1)),
            ("field_in_sensor_frame (one source)", lambda: field_in_sensor_frame(X_WS, sources))):
        print(f"  {label:44s}{median_us(fn):7.2f}")
    rng = np.random.default_rng(0)
    n = 360000
    draws = rng.standard_normal((3, n, 3))
    start = time.perf_counter()
    gyro.record(np.zeros(3), draws[0], draws[1], draws[2, 0])
    per_sample = (time.perf_counter() - start) / n * 1e6
    print(f"  {'ChannelNoise.record, per 3-axis sample':44s}{per_sample:7.3f}  ({n} samples)")


def build(variant, imu_config, mag_config):
    plant = MultibodyPlant(1e-3)
    capsule = plant.AddRigidBody(
        "capsule", SpatialInertia.SolidCylinderWithMass(0.012, 0.0058, 0.0315, [0, 0, 1]))
    plant.AddRigidBody("epm", SpatialInertia.SolidCylinderWithMass(6.2, 0.05, 0.1, [0, 0, 1]))
    plant.set_gravity_enabled(capsule.model_instance(), False)
    plant.Finalize()
    builder = DiagramBuilder()
    builder.AddSystem(plant)
    updates_per_second = 0.0
    if variant in ("+ Imu", "+ Imu + MahonyAhrs"):
        imu = builder.AddNamedSystem("capsule.imu", Imu(plant, capsule, imu_config))
        imu.connect_to_plant(builder, plant)
        updates_per_second = imu_config.sample_rate
        if variant == "+ Imu + MahonyAhrs":
            ahrs = builder.AddNamedSystem(
                "capsule.ahrs", MahonyAhrs(imu_config.sample_rate, AhrsConfig()))
            builder.Connect(imu.GetOutputPort("accel"), ahrs.get_accel_input_port())
            builder.Connect(imu.GetOutputPort("gyro"), ahrs.get_gyro_input_port())
    elif variant == "+ Magnetometer":
        sources = [MagnetSpec(name="ipm", body="capsule", p_BM=[0, 0, -0.003], moment=1.26),
                   MagnetSpec(name="epm", body="epm", moment=970.0)]
        mag = builder.AddNamedSystem("capsule.magnetometer",
                                     Magnetometer(plant, capsule, sources, mag_config))
        builder.Connect(plant.get_body_poses_output_port(), mag.get_body_poses_input_port())
        add_random_sources(builder, mag.get_noise_input_ports(), mag.period())
        updates_per_second = mag_config.sample_rate
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    diagram.SetRandomContext(context, RandomGenerator(1))
    plant_context = plant.GetMyMutableContextFromRoot(context)
    plant.SetFreeBodyPose(plant_context, capsule,
                          RigidTransform(RollPitchYaw(0.5, 0.0, 0.0), [0.0, 0.0, 0.0]))
    plant.SetFreeBodySpatialVelocity(plant_context, capsule,
                                     SpatialVelocity(w=[0.0, 0.1, 0.35], v=[0.0, 0.0, 0.0]))
    plant.SetFreeBodyPose(plant_context, plant.GetBodyByName("epm"),
                          RigidTransform([0.0, 0.0, 0.15]))
    simulator = Simulator(diagram, context)
    simulator.Initialize()
    return simulator, updates_per_second


def system_costs(sim_seconds, chunk=0.5):
    imu_config, mag_config = ImuConfig(), MagnetometerConfig()
    sims = {v: build(v, imu_config, mag_config) for v in VARIANTS}
    times = {v: [] for v in VARIANTS}
    t = 0.0
    while t < sim_seconds - 1e-9:
        t += chunk
        for v in VARIANTS:  # interleaved: load from other processes mostly cancels
            simulator = sims[v][0]
            start = time.perf_counter()
            simulator.AdvanceTo(t)
            times[v].append(time.perf_counter() - start)
    base = np.array(times["plant only"])
    print(f"simulation, 1 ms plant step, {sim_seconds:g} s simulated "
          f"(median over {len(base)} chunks of {chunk} s):")
    print(f"  plant only: {statistics.median(base) / chunk * 1e6 / 1000:7.1f} us per 1 ms step")
    for v in VARIANTS[1:]:
        extra = np.array(times[v]) - base
        rate = sims[v][1]
        per_update = statistics.median(extra) / (chunk * rate) * 1e6
        print(f"  {v:22s} adds {per_update:7.1f} us per {rate:g} Hz update "
              f"({statistics.median(extra) / chunk * 100:5.2f} % of real time)")
    return sims


def allan_figures(plot_path=None, hours=1.0, seed=0):
    config = ImuConfig()
    fs = config.sample_rate
    n = int(hours * 3600 * fs)
    rng = np.random.default_rng(seed)
    accel, gyro = imu_channels(config)
    a, _ = accel.record(np.array([0.0, 0.0, 9.81]), rng.standard_normal((n, 3)),
                        rng.standard_normal((n, 3)), rng.standard_normal(3))
    w, _ = gyro.record(np.zeros(3), rng.standard_normal((n, 3)),
                       rng.standard_normal((n, 3)), rng.standard_normal(3))
    print(f"Allan deviation of a {hours:g} h static recording, ImuConfig() defaults "
          f"({fs:g} Hz):")
    curves = {}
    for name, samples, density, walk, unit, scale in (
            ("accel", a, config.accel_noise_density, config.accel_bias_random_walk,
             "ug", 1e6 / 9.80665),
            ("gyro", w, config.gyro_noise_density, config.gyro_bias_random_walk,
             "deg/h", 3600 * 180 / math.pi)):
        tau, adev = allan_deviation(samples, 1.0 / fs)
        curves[name] = (tau, adev, density, walk, unit, scale)
        for axis in range(3):
            N = white_noise_coefficient(tau, adev[:, axis], tau_max=1.0)
            i = int(np.argmin(adev[:, axis]))
            print(f"  {name} {'xyz'[axis]}: N fit (tau <= 1 s) = {N:.4g} vs configured "
                  f"density / sqrt(2) = {density / math.sqrt(2):.4g} "
                  f"({(N / (density / math.sqrt(2)) - 1) * 100:+.1f} %); "
                  f"ADEV minimum {adev[i, axis] * scale:.3g} {unit} at tau = {tau[i]:.0f} s")
        white = density / math.sqrt(2)
        print(f"    predicted minimum sqrt(2 N K / sqrt(3)) = "
              f"{math.sqrt(2 * white * walk / math.sqrt(3)) * scale:.3g} {unit} at "
              f"tau = {math.sqrt(3) * white / walk:.0f} s")
    if plot_path:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
        for ax, (name, (tau, adev, density, walk, unit, scale)) in zip(axes, curves.items()):
            for axis in range(3):
                ax.loglog(tau, adev[:, axis] * scale, label=f"{name} {'xyz'[axis]}")
            white = density / math.sqrt(2)
            ax.loglog(tau, white / np.sqrt(tau) * scale, "k--", lw=1,
                      label="N / sqrt(tau), N = density / sqrt(2)")
            ax.loglog(tau, walk * np.sqrt(tau / 3) * scale, "k:", lw=1,
                      label="K sqrt(tau / 3)")
            ax.set_xlabel("tau (s)")
            ax.set_ylabel(f"Allan deviation ({unit})")
            ax.set_title(f"MPU-6050 {name}, static, {hours:g} h at {fs:g} Hz")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(plot_path, dpi=110)
        print(f"  plot written to {plot_path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-seconds", type=float, default=5.0)
    parser.add_argument("--plot", default="", help="write the Allan plot to this PNG")
    args = parser.parse_args()
    pure_function_costs()
    system_costs(args.sim_seconds)
    allan_figures(args.plot or None)


if __name__ == "__main__":
    main()
