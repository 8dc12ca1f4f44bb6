"""Record a dataset: the station with its camera and sensors, and a DatasetWriter."""

import dataclasses
from pathlib import Path

import yaml
from pydrake.systems.primitives import Demultiplexer, Multiplexer

from capsule_drake.io.dataset import DatasetWriter
from capsule_drake.io.mcap_log import add_mcap_logger
from capsule_drake.io.run import RunResult, chain_extends, simulate
from capsule_drake.scenario import Scenario
from capsule_drake.capsule.ahrs import AhrsConfig
from capsule_drake.capsule.camera import CameraConfig, camera_tick
from capsule_drake.capsule.imu import ImuConfig
from capsule_drake.capsule.magnetometer import MagnetometerConfig

# Sensor streams written as CSV files: file name -> [(station output, column names)].
_STREAMS = {
    "imu": [("capsule.imu.accel", ["ax", "ay", "az"]),
            ("capsule.imu.gyro", ["gx", "gy", "gz"]),
            ("capsule.imu.accel_true", ["ax_true", "ay_true", "az_true"]),
            ("capsule.imu.gyro_true", ["gx_true", "gy_true", "gz_true"])],
    "ahrs": [("capsule.ahrs.q_WB", ["qw", "qx", "qy", "qz"])],
    "magnetometer": [("capsule.magnetometer.B_S", ["bx", "by", "bz"]),
                     ("capsule.magnetometer.B_S_true", ["bx_true", "by_true", "bz_true"])],
    "ground_truth": [("capsule.state", ["qw", "qx", "qy", "qz", "x", "y", "z",
                                         "wx", "wy", "wz", "vx", "vy", "vz"])],
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


def _camera_yaml(camera, lens) -> str:
    config = dataclasses.asdict(camera.lens)
    intrinsics = {name: float(getattr(lens, name)) for name in ("fx", "fy", "cx", "cy")
                  if hasattr(lens, name)}
    text = {"lens": config, "intrinsics_px": intrinsics,
            "pixel_convention": "OpenCV: the first pixel's centre is (0, 0)",
            "depth": "range along each pixel's ray (m), not z-depth",
            "fps_mode": camera.fps_mode, "fps": camera.fps}
    return yaml.safe_dump(text, sort_keys=False)


def record(scenario: Scenario, out_dir: Path | str, *, progress: bool = True,
           mcap: Path | str | None = None) -> RunResult:
    """Simulates `scenario` with a camera and writes a dataset to `out_dir` as it runs.

    Also writes the run's metrics.json, scenario.yaml and logs.npz there (see `simulate`),
    and with `mcap` an MCAP file of ROS 2 messages (io/mcap_log.py) as well.
    """
    scenario = with_all_sensors(scenario)
    out_dir = Path(out_dir)
    camera_config = scenario.capsule.camera
    tick = camera_tick(camera_config)

    def extend(builder, station):
        camera = station.GetSubsystemByName("capsule.camera")
        plant = station.GetSubsystemByName("plant")
        X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
        streams, sources = [], []
        outputs = {station.get_output_port(i).get_name()
                   for i in range(station.num_output_ports())}
        for name, parts in _STREAMS.items():
            if not all(port in outputs for port, _ in parts):
                continue  # that sensor is switched off in the scenario
            columns = [c for _, cs in parts for c in cs]
            period = (scenario.outputs.log_period if name == "ground_truth" else
                      1.0 / scenario.capsule.imu.sample_rate if name in ("imu", "ahrs") else
                      1.0 / scenario.capsule.magnetometer.sample_rate)
            streams.append((name, columns, period))
            sources.append((name, parts))
        writer = builder.AddNamedSystem("dataset_writer", DatasetWriter(
            out_dir, X_BC, frame_check_period=tick, streams=streams,
            camera_yaml=_camera_yaml(camera_config, camera.lens)))
        builder.Connect(station.GetOutputPort("capsule.camera.rgb_image"),
                        writer.GetInputPort("rgb"))
        builder.Connect(station.GetOutputPort("capsule.camera.depth_image"),
                        writer.GetInputPort("depth"))
        # frame_info = [time of the last frame, frames taken, took-a-frame flag, rate].
        frame_info = builder.AddNamedSystem("frame_info", Demultiplexer([1, 3]))
        builder.Connect(station.GetOutputPort("capsule.camera.frame_info"),
                        frame_info.get_input_port(0))
        builder.Connect(frame_info.get_output_port(0), writer.GetInputPort("frame_time"))
        builder.Connect(station.GetOutputPort("capsule.state"),
                        writer.GetInputPort("capsule_state"))
        lumen = builder.AddNamedSystem("lumen_vector", Multiplexer([2, 1, 4]))
        for i, name in enumerate(("lumen_pixel", "lumen_visible", "lumen_point_W")):
            builder.Connect(station.GetOutputPort(f"capsule.lumen.{name}"),
                            lumen.get_input_port(i))
        builder.Connect(lumen.get_output_port(), writer.GetInputPort("lumen"))
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
