"""Cost of the magnetic localiser's update, and of the Hall-sensor array's sample.

Prints the median microseconds of:
  - one estimator update (`PoseEstimate.predict` + `update`: the gyroscope's step and the
    iterated update on four three-axis sensors and the accelerometer), as the
    `capsule.localizer` system runs it every 10 ms, for 1, 2 and 3 iterations;
  - the same inside Drake: the `MagneticLocalizer` system's periodic update in a Simulator
    (inputs fixed), i.e. with the state packing and the event dispatch;
  - one sample of the sensor array (`MagneticSensorArray`'s field of the finite EPM at the
    four sensors, the errors and the calibration).
The acceptance bound is 1 ms per update (so that the localiser at 100 Hz costs under 10 %
of real time).

Run: python benchmarks/bench_localization.py
"""

import dataclasses
import time

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator

from capsule_drake.capsule.magnetic_array import MagneticSensorArray, SensorErrors
from capsule_drake.epm.poses import field_aligning_moment_direction
from capsule_drake.navigation.localization import (LocalizerConfig, MagneticLocalizer,
                                                   PoseEstimate)
from capsule_drake.physics.magnetics import MagnetGeometry, cylinder_field
from timing import median_us  # benchmarks/timing.py


def main():
    epm = MagnetGeometry()
    ipm = MagnetGeometry(shape="cylinder", dimensions=[0.0111, 0.0111], remanence=1.48)
    plant = MultibodyPlant(0.0)
    body = plant.AddRigidBody("capsule", SpatialInertia.SolidSphereWithMass(0.01, 0.005))
    plant.Finalize()
    array = MagneticSensorArray(plant, body, [], ipm, RigidTransform([0.0, 0.0, -0.003]))
    rng = np.random.default_rng(0)
    # A capsule heading along y, the EPM 22 cm above and a little ahead (the follower's).
    R_WB = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    p_WB = np.zeros(3)
    p_E = np.array([0.0, 0.03, 0.22])
    m_hat = field_aligning_moment_direction((p_WB - p_E) / np.linalg.norm(p_WB - p_E),
                                            np.array([0.0, 1.0, 0.0]))
    positions = np.asarray(array.config.positions)
    errors = SensorErrors(array.config, rng.normal(size=SensorErrors.size(4)))
    B_epm = cylinder_field(epm.moment() * m_hat, p_WB + positions @ R_WB.T - p_E,
                           *epm.dimensions) @ R_WB
    B = (array.measure(B_epm, errors, rng.normal(size=(4, 3)))
         - array.calibration(errors)).ravel()
    accel = R_WB.T @ [0.0, 0.0, 9.81]
    gyro = np.zeros(3)
    epm_pose = np.concatenate([p_E, m_hat])
    saturated = np.zeros(4)

    print("estimator update (predict + iterated update), 4 sensors + accelerometer:")
    for iterations in (1, 2, 3):
        config = dataclasses.replace(LocalizerConfig(), iterations=iterations)
        estimate = PoseEstimate(config, positions, array.self_field(), epm.moment())
        estimate.reset(p_WB, R_WB)

        def step():
            estimate.predict(gyro, config.period)
            estimate.update(B, saturated, accel, epm_pose)

        print(f"  {iterations} iteration(s): {median_us(step, repeats=5, number=400):7.1f} us")

    config = LocalizerConfig()
    localizer = MagneticLocalizer(
        PoseEstimate(config, positions, array.self_field(), epm.moment()),
        RigidTransform(p_WB))
    context = localizer.CreateDefaultContext()
    for name, value in (("B", B), ("saturated", saturated), ("accel", accel), ("gyro", gyro),
                        ("epm_pose", epm_pose)):
        localizer.GetInputPort(name).FixValue(context, value)
    simulator = Simulator(localizer, context)
    steps = 1000
    start = time.perf_counter()
    simulator.AdvanceTo(steps * config.period)
    per_update = 1e6 * (time.perf_counter() - start) / steps
    print(f"MagneticLocalizer in a Simulator ({config.iterations} iterations): "
          f"{per_update:7.1f} us per update")

    def sample():
        field = cylinder_field(epm.moment() * m_hat, p_WB + positions @ R_WB.T - p_E,
                               *epm.dimensions) @ R_WB
        raw = array.measure(field, errors, rng.normal(size=(4, 3)))
        return raw - array.calibration(errors)

    print(f"array sample (finite EPM field at 4 sensors, errors, calibration): "
          f"{median_us(sample, repeats=5, number=400):7.1f} us")


if __name__ == "__main__":
    main()
