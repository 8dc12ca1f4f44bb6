"""Record a dataset: the station with its camera and sensors, and a DatasetWriter."""

import dataclasses
import sys
from pathlib import Path

from pydrake.systems.primitives import Demultiplexer, Multiplexer

from capsule_drake.app.dataset import DatasetWriter, PlantTiming, Stream
from capsule_drake.app.dataset_docs import (SPLIT_RULE, DatasetDescription, camera_yaml,
                                           dataset_readme, sensors_yaml, split_counts,
                                           split_of_seed, splits_readme)
from capsule_drake.app.outputs import SEED_PREFIX, write_atomic
from capsule_drake.app.run import RunResult, simulate
from capsule_drake.station import station_value
from capsule_drake.scenario import McapOutput, Scenario, ScenarioError
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

    Also writes the run's metrics.json, scenario.yaml, logs.npz and the wall's pressure map
    (wall_pressure.npz, .png) there (see `simulate`),
    and with `mcap` an MCAP file of ROS 2 messages (app/mcap_log.py) as well.
    """
    scenario = with_all_sensors(scenario)
    out_dir = Path(out_dir)
    camera_config = scenario.capsule.camera
    tick = camera_tick(camera_config)

    def extend(builder, station):
        lens = station_value(station, "capsule.camera.lens")
        plant = station_value(station, "scene.plant")
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
            lens=lens, camera=camera_config, X_BC=X_BC, streams=streams,
            imu=scenario.capsule.imu, magnetometer=scenario.capsule.magnetometer,
            ahrs=scenario.capsule.ahrs, scenario_name=scenario_name,
            colon_seed=getattr(scenario.colon, "seed", 0), random_seed=scenario.random_seed,
            duration=scenario.duration, depth_full_scale=camera_config.far,
            sensor_lag=sensor_lag, polyps=len(polyps))
        writer = builder.AddNamedSystem("dataset_writer", DatasetWriter(
            out_dir, frame_check_period=tick, frame_check_offset=camera_config.latency,
            streams=streams, mask=lens.pixel_rays()[1],
            depth_full_scale=camera_config.far, lumen_truth=station_value(station, "capsule.lumen.truth_at"),
            far_truth=station_value(station, "capsule.lumen.far_at"),
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

    if mcap is not None:   # the scenario's outputs.mcap, at this path
        scenario = dataclasses.replace(scenario, outputs=dataclasses.replace(
            scenario.outputs, mcap=McapOutput(path=str(mcap))))
    return simulate(scenario, out_dir=out_dir, progress=progress, extend=extend)


@dataclasses.dataclass
class SeedBatch:
    """What `record_seeds` recorded: the seeds recorded and failed, the splits' counts of
    those recorded, and the result of a recording that was interrupted (the batch stops)."""

    recorded: list
    failed: list
    counts: dict
    interrupted: RunResult | None = None


def record_seeds(scenario_of, seeds, fractions, out_dir: Path, name: str, *,
                 quiet: bool = False, on_stop=None) -> SeedBatch:
    """One dataset per colon seed into out_dir/seed_XXXX/ (`record` of `scenario_of(seed)`),
    with splits.csv and README.md: written first as planned (a batch cut short keeps its
    plan), and again over the seeds recorded. A seed whose scenario fails (a colon with no
    course) is counted failed and the others go on; an interrupted recording ends the
    batch. `on_stop(result)`: told of each recording's result (to report an early stop)."""
    width = max(4, len(str(max(seeds))))
    folders = {seed: f"{SEED_PREFIX}{seed:0{width}d}" for seed in seeds}
    splits = {seed: split_of_seed(seed, fractions) for seed in seeds}

    def write_splits(recorded):
        rows = ["seed,split,folder"] + [f"{seed},{splits[seed]},{folders[seed]}"
                                        for seed in recorded]
        write_atomic(out_dir / "splits.csv", "\n".join(rows) + "\n")
        counts = split_counts(recorded, fractions)
        write_atomic(out_dir / "README.md", splits_readme(SPLIT_RULE, fractions, counts))
        return counts

    counts = write_splits(seeds)  # the plan, in case the batch is cut short
    print(f"recording {len(seeds)} colon seeds into {out_dir}/: "
          + ", ".join(f"{split} {n}" for split, n in counts.items()), file=sys.stderr)
    recorded, failed = [], []
    for k, seed in enumerate(seeds):
        print(f"seed {seed} ({k + 1}/{len(seeds)}, {splits[seed]}) -> {folders[seed]}/",
              file=sys.stderr)
        try:
            result = record(scenario_of(seed), out_dir / folders[seed], progress=not quiet,
                            scenario_name=name)
        except ScenarioError as e:  # e.g. a colon seed with no course: the others go on
            print(f"seed {seed}: error: {e}", file=sys.stderr)
            failed.append(seed)
            continue
        if on_stop is not None:
            on_stop(result)
        if result.status == "interrupted":
            return SeedBatch(recorded, failed, write_splits(recorded), result)
        (recorded if result.status in ("completed", "goal") else failed).append(seed)
    return SeedBatch(recorded, failed, write_splits(recorded))

