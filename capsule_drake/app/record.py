"""Record a dataset: the station with its camera and sensors, and a DatasetWriter."""

import dataclasses
from pathlib import Path

from pydrake.systems.primitives import Demultiplexer, Multiplexer

from capsule_drake.app.dataset import DatasetWriter, PlantTiming, Stream
from capsule_drake.app.dataset_docs import (DatasetDescription, camera_yaml, dataset_readme,
                                           sensors_yaml)
from capsule_drake.app.mcap_log import add_mcap_logger
from capsule_drake.app.run import RunResult, chain_extends, simulate
from capsule_drake.scenario import Scenario
from capsule_drake.capsule.ahrs import AhrsConfig
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.camera_config import CameraConfig, camera_tick
from capsule_drake.capsule.imu import ImuConfig
from capsule_drake.capsule.magnetometer import MagnetometerConfig

# Sensor streams written as CSV files: file name -> ([(station output, column names)],
# the order of the inputs' entries in the columns, or None). Units end the names; quaternions
# are put in x, y, z, w order (the station's are w, x, y, z).
_STREAMS = {
    "imu": ([("capsule.imu.accel", ["ax_m_s2", "ay_m_s2", "az_m_s2"]),
             ("capsule.imu.gyro", ["gx_rad_s", "gy_rad_s", "gz_rad_s"]),
             ("capsule.imu.accel_true", ["ax_true_m_s2", "ay_true_m_s2", "az_true_m_s2"]),
             ("capsule.imu.gyro_true", ["gx_true_rad_s", "gy_true_rad_s", "gz_true_rad_s"])],
            None),
    "ahrs": ([("capsule.ahrs.q_WB", ["qx", "qy", "qz", "qw"])], (1, 2, 3, 0)),
    "magnetometer": ([("capsule.magnetometer.B_S", ["bx_T", "by_T", "bz_T"]),
                      ("capsule.magnetometer.B_S_true", ["bx_true_T", "by_true_T",
                                                         "bz_true_T"])], None),
    # capsule.state is [q_WB (w, x, y, z), p_WB, w_WB, v_WB]: written p, q (x, y, z, w), w, v.
    "ground_truth": ([("capsule.state", ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw",
                                         "wx_rad_s", "wy_rad_s", "wz_rad_s",
                                         "vx_m_s", "vy_m_s", "vz_m_s"])],
                     (4, 5, 6, 1, 2, 3, 0, 7, 8, 9, 10, 11, 12)),
}


def with_all_sensors(scenario: Scenario) -> Scenario:
    """The scenario with a camera, IMU, AHRS and magnetometer: its own where it has them,
    the defaults where it does not. The original is kept."""
    capsule = scenario.capsule
    return dataclasses.replace(scenario, capsule=dataclasses.replace(
        capsule,
        camera=capsule.camera if capsule.camera is not None else CameraConfig(),
        imu=capsule.imu if capsule.imu is not None else ImuConfig(),
        ahrs=capsule.ahrs if capsule.ahrs is not None else AhrsConfig(),
        magnetometer=(capsule.magnetometer if capsule.magnetometer is not None
                      else MagnetometerConfig())))


def record(scenario: Scenario, out_dir: Path | str, *, progress: bool = True,
           scenario_name: str = "", mcap: Path | str | None = None) -> RunResult:
    """Simulates `scenario` with a camera and writes a dataset to `out_dir` as it runs
    (app/dataset.py; its README.md describes it, naming the scenario `scenario_name`).

    Also writes the run's metrics.json, scenario.yaml and logs.npz there (see `simulate`),
    and with `mcap` an MCAP file of ROS 2 messages (app/mcap_log.py) as well.
    """
    scenario = with_all_sensors(scenario)
    out_dir = Path(out_dir)
    camera_config = scenario.capsule.camera
    tick = camera_tick(camera_config)

    def extend(builder, station):
        camera = station.GetSubsystemByName("capsule.camera")
        plant = station.GetSubsystemByName("plant")
        X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
        imu_period = 1.0 / scenario.capsule.imu.sample_rate
        periods = {"imu": imu_period, "ahrs": imu_period,
                   "magnetometer": 1.0 / scenario.capsule.magnetometer.sample_rate,
                   "ground_truth": scenario.outputs.log_period}
        # A discrete plant with sampled output ports steps in an unrestricted update, which
        # Drake runs before the discrete updates at the same time: a sensor's sample at t
        # then measures the state one plant step later (app/dataset.py, state_time).
        timing = PlantTiming.of(plant)
        plant_step, plant_step_first = timing.step, timing.step_first
        sensor_lag = plant_step if plant_step > 0 and plant_step_first else 0.0
        streams, sources = [], []
        outputs = {station.get_output_port(i).get_name()
                   for i in range(station.num_output_ports())}
        for name, (parts, order) in _STREAMS.items():
            if not all(port in outputs for port, _ in parts):
                continue  # that sensor is switched off in the scenario
            streams.append(Stream(
                name, tuple(c for _, cs in parts for c in cs), periods[name],
                # The plant's state is read at the sample time; a sensor's just after its
                # update there. The AHRS's first estimate is of the attitude one IMU period
                # in (it steps the first IMU sample forward).
                after_update=name != "ground_truth",
                first_sample=imu_period if name == "ahrs" else 0.0, order=order))
            sources.append((name, parts))
        polyps = lesion_scene(scenario.colon).lesions if station.HasOutputPort(
            "capsule.camera.label_image") else []
        description = DatasetDescription(
            lens=camera.lens, camera=camera_config, X_BC=X_BC, streams=streams,
            imu=scenario.capsule.imu, magnetometer=scenario.capsule.magnetometer,
            ahrs=scenario.capsule.ahrs, scenario_name=scenario_name,
            colon_seed=getattr(scenario.colon, "seed", 0), random_seed=scenario.random_seed,
            duration=scenario.duration, depth_full_scale=camera_config.far,
            sensor_lag=sensor_lag, polyps=len(polyps))
        lumen = station.GetSubsystemByName("capsule.lumen")
        writer = builder.AddNamedSystem("dataset_writer", DatasetWriter(
            out_dir, frame_check_period=tick, frame_check_offset=camera_config.latency,
            streams=streams, mask=camera.lens.pixel_rays()[1],
            depth_full_scale=camera_config.far, lumen_truth=lumen.truth_at,
            plant_step=plant_step, plant_step_first=plant_step_first, polyps=polyps,
            texts={"README.md": dataset_readme(description),
                   "camera.yaml": camera_yaml(description),
                   "sensors.yaml": sensors_yaml(description)}))
        builder.Connect(station.GetOutputPort("capsule.camera.rgb_image"),
                        writer.GetInputPort("rgb"))
        builder.Connect(station.GetOutputPort("capsule.camera.depth_image"),
                        writer.GetInputPort("depth"))
        builder.Connect(station.GetOutputPort("capsule.camera.frame_pose"),
                        writer.GetInputPort("frame_pose"))
        if polyps:
            builder.Connect(station.GetOutputPort("capsule.camera.label_image"),
                            writer.GetInputPort("labels"))
        # frame_info = [exposure time of the last frame, frames taken, took-a-frame flag, rate].
        frame_info = builder.AddNamedSystem("frame_info", Demultiplexer([1, 3]))
        builder.Connect(station.GetOutputPort("capsule.camera.frame_info"),
                        frame_info.get_input_port(0))
        builder.Connect(frame_info.get_output_port(0), writer.GetInputPort("frame_time"))
        for name, parts in sources:
            mux = builder.AddNamedSystem(f"{name}_vector", Multiplexer([len(c) for _, c in parts]))
            for i, (port, _) in enumerate(parts):
                builder.Connect(station.GetOutputPort(port), mux.get_input_port(i))
            builder.Connect(mux.get_output_port(), writer.GetInputPort(name))
        return writer.close

    def extend_mcap(builder, station):
        return add_mcap_logger(builder, station, scenario, mcap).close

    return simulate(scenario, out_dir=out_dir, progress=progress,
                    extend=chain_extends(extend, extend_mcap if mcap is not None else None))
