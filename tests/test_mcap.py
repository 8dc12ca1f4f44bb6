"""MCAP logs of ROS 2 messages (app/mcap_log.py, app/ros2_messages.py), read back with the
`mcap` library and the `mcap_ros2` decoder, and checked against independent routes: the
message definitions against the `rosbags` package's copy of ROS 2's, the payloads against
its CDR decoder, the images against the dataset's PNGs of the same run, every stamp against
the dataset's times of the same samples, the poses against logs.npz, the camera model against
OpenCV's fisheye projection, the IMU's frame against gravity, its stamps against the ground
truth's angular velocity, and the Hall sensors' frames against the EPM's dipole field."""

import collections
import csv
from unittest import mock

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from capsule_drake.app.cli import main as cli_main
from capsule_drake.app.dataset import read_depth_png
from capsule_drake.app import mcap_file
from capsule_drake.app.mcap_file import Ros2McapFile, check_mcap_path
from capsule_drake.app.mcap_log import add_mcap_logger
from capsule_drake.app.outputs import OutputError
from capsule_drake.app.ros2_messages import DEFINITIONS, schema_text
from capsule_drake.app.run import chain_extends, simulate
from capsule_drake.perception.lens import Lens
from capsule_drake.perception.lumen_truth import far_region
from capsule_drake.physics.magnetics import dipole_field
from capsule_drake.scenario import load_scenario

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)


def read_mcap(path):
    """(summary, {topic: [(log_time ns, decoded message, raw CDR bytes, type name)]})."""
    messages = collections.defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        header = reader.get_header()
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            messages[channel.topic].append((message.log_time, decoded, message.data, schema.name))
    return header, summary, messages


def seconds(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def transforms(messages, child):
    """{stamp (s): (p, q wxyz)} of a child frame on /tf."""
    found = {}
    for _, tf, _, _ in messages["/tf"]:
        for t in tf.transforms:
            if t.child_frame_id == child:
                r, p = t.transform.rotation, t.transform.translation
                found[round(seconds(t.header.stamp), 6)] = (np.array([p.x, p.y, p.z]),
                                                             np.array([r.w, r.x, r.y, r.z]))
    return found


def static_transform(messages, child) -> RigidTransform:
    (_, tf, _, _), = messages["/tf_static"]
    t, = [t for t in tf.transforms if t.child_frame_id == child]
    r, p = t.transform.rotation, t.transform.translation
    return RigidTransform(Quaternion(r.w, r.x, r.y, r.z), [p.x, p.y, p.z])


def pose(p, q) -> RigidTransform:
    return RigidTransform(Quaternion(q / np.linalg.norm(q)), p)


def test_definitions_are_ros2s():
    # The field lists written here against the rosbags package's copy of ROS 2 Humble's
    # (generated from the interface packages): names, types, array sizes and constants.
    for name in DEFINITIONS:
        assert get_types_from_msg(DEFINITIONS[name], name)[name] == HUMBLE.fielddefs[name], name
    # Each schema names the types it uses, each once after the 80-'=' delimiter, as rosbags
    # concatenates them (its own implementation of the format).
    for name in DEFINITIONS:
        theirs = HUMBLE.generate_msgdef(name, ros_version=2)[0]
        delimiter = "=" * 80 + "\nMSG: "
        assert ([part.split("\n")[0] for part in schema_text(name).split(delimiter)[1:]]
                == [part.split("\n")[0] for part in theirs.split(delimiter)[1:]]), name


def test_a_bad_mcap_path_is_one_line_and_status_2(tmp_path, capsys):
    missing = tmp_path / "no_such_folder" / "run.mcap"
    assert cli_main(["run", "--duration", "0.1", "--mcap", str(missing), "--quiet",
                     "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "does not exist" in err, err
    assert not (tmp_path / "out").exists()  # refused before anything was made or run
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"x")
    assert cli_main(["record", "--duration", "0.1", "--mcap", str(existing), "--quiet",
                     "--out", str(tmp_path / "data")]) == 2
    assert "exists" in capsys.readouterr().err and existing.read_bytes() == b"x"
    with pytest.raises(OutputError, match="is a folder"):
        check_mcap_path(tmp_path)
    with pytest.raises(OutputError, match="MB free"):
        check_mcap_path(tmp_path / "big.mcap", expected_bytes=1e18)


PLANT_STEP = 0.002  # WithSensors' plant.time_step (s)


def read_csv(path):
    return np.genfromtxt(path, delimiter=",", names=True)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """`record --scenario WithSensors --mcap` for 1 s: the dataset and the MCAP of one run,
    with the IMU turned on the board (so its frame differs from the capsule's), and /tf and
    the ground truth at every plant step (so every sensor stamp has its state there)."""
    folder = tmp_path_factory.mktemp("mcap")
    out, path = folder / "dataset", folder / "run.mcap"
    code = cli_main(["record", "--scenario", "WithSensors", "--duration", "1.0", "--quiet",
                     "--scenario-text", "{capsule: {imu: {rpy_BS_deg: [0.0, 0.0, 90.0]}}, "
                     f"outputs: {{log_period: {PLANT_STEP}}}}}",
                     "--out", str(out), "--mcap", str(path)])
    assert code == 0
    return out, read_mcap(path)


@pytest.mark.slow
def test_channels_have_ros2_schemas(recorded):
    _, (header, summary, messages) = recorded
    assert header.profile == "ros2"
    types = {}
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
        assert "offered_qos_profiles" in channel.metadata
        types[channel.topic] = schema.name
    assert types["/capsule/camera/image_raw"] == "sensor_msgs/msg/Image"
    assert types["/capsule/camera/camera_info"] == "sensor_msgs/msg/CameraInfo"
    assert types["/capsule/camera/depth/image_raw"] == "sensor_msgs/msg/Image"
    assert types["/capsule/imu/data"] == "sensor_msgs/msg/Imu"
    assert types["/capsule/magnetometer"] == "sensor_msgs/msg/MagneticField"
    assert types["/tf"] == types["/tf_static"] == "tf2_msgs/msg/TFMessage"
    assert types["/capsule/contact/wrench"] == "geometry_msgs/msg/WrenchStamped"
    assert types["/capsule/contact/peak_pressure"] == "sensor_msgs/msg/FluidPressure"
    assert types["/capsule/lumen_tracker/pixel"] == "geometry_msgs/msg/PointStamped"
    # Every payload is what ROS 2's definitions make of it: decoded by an independent CDR
    # implementation (rosbags, with its copy of the Humble interfaces) and encoded again, it
    # gives back the same bytes.
    for topic, items in messages.items():
        for _, _, raw, name in (items[0], items[-1]):
            again = HUMBLE.serialize_cdr(HUMBLE.deserialize_cdr(raw, name), name)
            assert bytes(again) == raw, topic


@pytest.mark.slow
def test_run_with_sensors_writes_the_ros2_channels(tmp_path):
    # The acceptance's command itself: `run --scenario WithSensors --mcap FILE`, read back
    # with the mcap library: image, IMU, magnetic-field and tf channels with ROS 2 schemas,
    # each with messages that decode, stamped on the run's clock.
    path = tmp_path / "run.mcap"
    code = cli_main(["run", "--scenario", "WithSensors", "--duration", "0.3", "--quiet",
                     "--no-recording", "--out", str(tmp_path / "run"), "--mcap", str(path)])
    assert code == 0
    header, summary, messages = read_mcap(path)
    assert header.profile == "ros2"
    types = {channel.topic: summary.schemas[channel.schema_id].name
             for channel in summary.channels.values()}
    for topic, name in [("/capsule/camera/image_raw", "sensor_msgs/msg/Image"),
                        ("/capsule/imu/data", "sensor_msgs/msg/Imu"),
                        ("/capsule/magnetometer", "sensor_msgs/msg/MagneticField"),
                        ("/tf", "tf2_msgs/msg/TFMessage"),
                        ("/tf_static", "tf2_msgs/msg/TFMessage")]:
        assert types[topic] == name, topic
        assert messages[topic], topic
        schema = next(summary.schemas[c.schema_id] for c in summary.channels.values()
                      if c.topic == topic)
        assert schema.encoding == "ros2msg"
    image = messages["/capsule/camera/image_raw"][-1][1]
    assert image.encoding == "rgb8" and len(image.data) == image.height * image.step > 0
    imu = messages["/capsule/imu/data"][-1][1]
    assert 5.0 < np.linalg.norm([imu.linear_acceleration.x, imu.linear_acceleration.y,
                                 imu.linear_acceleration.z]) < 15.0  # gravity, +- motion
    field = messages["/capsule/magnetometer"][-1][1].magnetic_field
    assert 0.0 < np.linalg.norm([field.x, field.y, field.z]) < 1.0  # tesla
    children = {t.child_frame_id for _, tf, _, _ in messages["/tf"] for t in tf.transforms}
    assert {"capsule", "epm"} <= children
    last = max(t for items in messages.values() for t, _, _, _ in items)
    assert 0.25e9 <= last <= 0.3e9 + 1e6


@pytest.mark.slow
def test_messages_have_the_right_sizes_and_times(recorded):
    _, (_, _, messages) = recorded
    for topic, items in messages.items():
        log_times = [t for t, _, _, _ in items]
        assert np.all(np.diff(log_times) > 0), topic  # one message per topic per event
        if topic == "/scene/markers":   # latched, once: the scene (app/scene_markers.py)
            assert len(items) == 1 and items[0][1].markers[0].ns == "colon_wall"
            continue
        stamps = [seconds(m.header.stamp) if hasattr(m, "header") else
                  seconds(m.transforms[0].header.stamp) for _, m, _, _ in items]
        assert np.all(np.diff(stamps) > 0), topic
        # Logged when produced: a sensor's sample (of the state one plant step after its
        # tick) just after its tick, before its stamp; anything else at or after its stamp.
        assert all(s * 1e9 <= t + PLANT_STEP * 1e9 + 1
                   for s, (t, _, _, _) in zip(stamps, items)), topic
    images = [m for _, m, _, _ in messages["/capsule/camera/image_raw"]]
    assert len(images) == 10  # 10 frames/s, the one at 1 s not yet taken
    for image in images:
        assert (image.encoding, image.width, image.height, image.step) == ("rgb8", 256, 256, 768)
        assert len(image.data) == 256 * 768
    depth = messages["/capsule/camera/depth/image_raw"][0][1]
    assert (depth.encoding, depth.step, len(depth.data)) == ("32FC1", 1024, 256 * 1024)
    imu = [m for _, m, _, _ in messages["/capsule/imu/data"]]
    assert len(imu) == 100 and imu[0].header.frame_id == "capsule_imu"
    # ROS's "no orientation" until the AHRS's first estimate (with the second sample), then
    # an orientation with its covariance unknown (all zeros).
    assert imu[0].orientation_covariance[0] == -1.0
    assert all(list(m.orientation_covariance) == [0.0] * 9 for m in imu[1:])
    field = messages["/capsule/magnetometer"][0][1]
    assert field.header.frame_id == "capsule_magnetometer"
    assert len(messages["/tf"]) == 501  # every plant step from 0 to 1 s, as logs.npz


@pytest.mark.slow
def test_images_are_the_datasets_frames(recorded):
    out, (_, _, messages) = recorded
    with open(out / "frames.csv") as f:
        frames = [(int(row["index"]), float(row["time_s"])) for row in csv.DictReader(f)]
    images = messages["/capsule/camera/image_raw"]
    depths = messages["/capsule/camera/depth/image_raw"]
    info = messages["/capsule/camera/camera_info"][0][1]
    lens = Lens(load_scenario(name="WithSensors").capsule.camera.lens)
    rays = lens.unproject(lens.pixel_grid()).reshape(256, 256, 3)
    assert len(frames) == len(images)
    # Both stamp a frame with the time of the state it shows: its exposure, or the next
    # plant step's when rounding puts the tick just after a step (0.302 s here).
    assert any(abs(t - 0.302) < 1e-9 for _, t in frames)
    for (index, time), (_, image, _, _), (_, depth, _, _) in zip(frames, images, depths):
        assert abs(seconds(image.header.stamp) - time) < 1e-9
        assert depth.header.stamp == image.header.stamp
        png = cv2.cvtColor(cv2.imread(str(out / "Frames" / f"FrameBuffer_{index:04d}.png")),
                           cv2.COLOR_BGR2RGB)
        rgb = np.frombuffer(bytes(image.data), np.uint8).reshape(256, 256, 3)
        np.testing.assert_array_equal(rgb, png)  # the same pixels
        assert rgb.std() > 10.0  # and not blank
        # Depth: z along the optical axis (REP 118) = the dataset's range x the ray's z.
        z = np.frombuffer(bytes(depth.data), "<f4").reshape(256, 256)
        range_png = read_depth_png(out / "Frames" / f"Depth_{index:04d}.png")
        seen = np.isfinite(z) & (range_png < 0.19)
        assert seen.mean() > 0.5
        np.testing.assert_allclose(z[seen], range_png[seen] * rays[..., 2][seen], atol=1e-5)
        assert np.all(np.isnan(z[~lens.in_field(rays.reshape(-1, 3)).reshape(256, 256)]))
    assert info.distortion_model == "equidistant" and list(info.d) == [0.0] * 4
    assert info.k[0] == pytest.approx(lens.fx) and info.k[2] == pytest.approx(lens.cx)


@pytest.mark.slow
def test_tf_is_the_logged_state(recorded):
    out, (_, _, messages) = recorded
    logs = np.load(out / "logs.npz")
    capsule, epm = transforms(messages, "capsule"), transforms(messages, "epm")
    assert len(capsule) == len(logs["times"])
    for k in range(0, len(logs["times"]), 7):
        p, q = capsule[round(float(logs["times"][k]), 6)]
        state = logs["capsule_state"][:, k]
        np.testing.assert_allclose(p, state[4:7], atol=1e-12)
        q_log = state[:4] / np.linalg.norm(state[:4])
        assert abs(abs(q @ q_log) - 1.0) < 1e-12  # the same rotation (q and -q)
        p_E, q_E = epm[round(float(logs["times"][k]), 6)]
        np.testing.assert_allclose(p_E, logs["epm_pose"][:3, k], atol=1e-12)
        # The EPM frame's +z is its moment.
        np.testing.assert_allclose(pose(p_E, q_E).rotation().col(2), logs["epm_pose"][3:, k],
                                   atol=1e-9)


@pytest.mark.slow
def test_sensor_stamps_are_the_datasets_times_and_tf_the_state_they_saw(recorded):
    # The same samples in both files of one run: each IMU, AHRS and magnetometer message
    # stamped with its dataset row's time (the state it measured, one plant step after the
    # tick) and carrying its values.
    out, (_, _, messages) = recorded
    imu_csv, ahrs_csv = read_csv(out / "imu.csv"), read_csv(out / "ahrs.csv")
    field_csv, truth = read_csv(out / "magnetometer.csv"), read_csv(out / "ground_truth.csv")
    imu = [m for _, m, _, _ in messages["/capsule/imu/data"]]
    stamps = np.array([seconds(m.header.stamp) for m in imu])
    assert len(imu) == len(imu_csv)
    np.testing.assert_allclose(stamps, imu_csv["time_s"], rtol=0, atol=1e-9)
    assert stamps[0] == pytest.approx(PLANT_STEP, abs=1e-9)
    for m, row in zip(imu, imu_csv):
        a, w = m.linear_acceleration, m.angular_velocity
        np.testing.assert_allclose([a.x, a.y, a.z, w.x, w.y, w.z],
                                   [row[k] for k in ("ax_m_s2", "ay_m_s2", "az_m_s2",
                                                     "gx_rad_s", "gy_rad_s", "gz_rad_s")],
                                   rtol=1e-8, atol=1e-12)
    fields = [m for _, m, _, _ in messages["/capsule/magnetometer"]]
    assert len(fields) == len(field_csv)
    for m, row in zip(fields, field_csv):
        assert abs(seconds(m.header.stamp) - row["time_s"]) < 1e-9
        B = m.magnetic_field
        np.testing.assert_allclose([B.x, B.y, B.z], [row["bx_T"], row["by_T"], row["bz_T"]],
                                   rtol=1e-8, atol=1e-15)
    # The AHRS's orientation of the IMU frame, from the second message on (the first says
    # "no orientation": the dataset has no row there), is its row of ahrs.csv turned by the
    # IMU's mounting.
    X_BS = static_transform(messages, "capsule_imu")
    R_BS = X_BS.rotation().matrix()
    np.testing.assert_allclose(stamps[1:], ahrs_csv["time_s"], rtol=0, atol=1e-9)
    for m, row in zip(imu[1:], ahrs_csv):
        o = m.orientation
        R_WS = Quaternion(o.w, o.x, o.y, o.z).rotation()
        R_WB = Quaternion(row["qw"], row["qx"], row["qy"], row["qz"]).rotation()
        np.testing.assert_allclose(R_WS, R_WB @ R_BS, atol=1e-8)
    # /tf at a sample's stamp is the state the sample saw: the IMU's ideal rate (imu.csv's
    # gyro_true) is the angular velocity of the state at that time (ground_truth.csv, in
    # world) turned into S by the /tf and /tf_static there. The state one plant step
    # earlier, what the old stamps pointed to, is far off while the capsule moves.
    capsule = transforms(messages, "capsule")
    rows = np.searchsorted(truth["time_s"], stamps - 1e-7)
    np.testing.assert_allclose(truth["time_s"][rows], stamps, rtol=0, atol=1e-9)
    w_W = np.column_stack([truth["wx_rad_s"], truth["wy_rad_s"], truth["wz_rad_s"]])
    gyro_true = np.column_stack([imu_csv["gx_true_rad_s"], imu_csv["gy_true_rad_s"],
                                 imu_csv["gz_true_rad_s"]])
    errors = {}
    for shift in (0, 1):
        predicted = []
        for row in rows - shift:
            p, q = capsule[round(float(truth["time_s"][row]), 6)]
            np.testing.assert_allclose(p, [truth[k][row] for k in ("x_m", "y_m", "z_m")],
                                       atol=1e-9)
            R_WB = pose(p, q).rotation().matrix()
            predicted.append(R_BS.T @ R_WB.T @ w_W[row])
        errors[shift] = np.abs(np.array(predicted) - gyro_true).max()
    assert errors[0] < 1e-6 and errors[1] > 0.1, errors


@pytest.mark.slow
def test_camera_model_projects_the_lumen_truth(recorded):
    # The lumen truth's world point, carried into the camera by /tf and /tf_static and
    # projected by OpenCV's fisheye model with the CameraInfo's K and D, lands on the truth's
    # pixel (computed by the simulator's own lens model), with /tf at the truth's stamp:
    # the pose it was computed from.
    _, (_, _, messages) = recorded
    X_BC = static_transform(messages, "capsule_camera_optical_frame")
    capsule = transforms(messages, "capsule")
    info = messages["/capsule/camera/camera_info"][-1][1]
    K, D = np.array(info.k).reshape(3, 3), np.array(info.d)
    errors = []
    for (_, pixel, _, _), (_, point, _, _) in zip(messages["/capsule/lumen_truth/pixel"],
                                                   messages["/capsule/lumen_truth/point"]):
        t = round(seconds(pixel.header.stamp), 6)
        if pixel.point.z != 1.0:
            continue  # not visible
        X_WC = pose(*capsule[t]).multiply(X_BC)
        p_C = X_WC.inverse().multiply([point.point.x, point.point.y, point.point.z])
        uv, _ = cv2.fisheye.projectPoints(p_C.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, D)
        errors.append(np.linalg.norm(uv.ravel() - [pixel.point.x, pixel.point.y]))
    print(f"lumen truth: OpenCV vs the lens model, largest {max(errors):.2g} px")
    assert len(errors) >= 5 and max(errors) < 0.01


@pytest.mark.slow
def test_far_region_topic_is_the_far_region_of_the_logged_depth(recorded):
    # The image-side truth on /capsule/lumen_truth/far_pixel, recomputed here from the same
    # frame's REP 118 depth (range = z over the ray's z; +inf kept as nothing within the
    # clip, NaN outside the field), lands on the same pixel with the same verdict.
    _, (_, _, messages) = recorded
    scenario = load_scenario(name="WithSensors")
    lens = Lens(scenario.capsule.camera.lens)
    rays, field = lens.pixel_rays()
    depths = messages["/capsule/camera/depth/image_raw"]
    fars = messages["/capsule/lumen_truth/far_pixel"]
    assert len(fars) == len(depths) >= 5
    seen = 0
    for (_, depth, _, _), (_, far, _, _) in zip(depths, fars):
        assert seconds(far.header.stamp) == seconds(depth.header.stamp)
        z = np.frombuffer(bytes(depth.data), "<f4").reshape(256, 256).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            range_m = np.where(np.isinf(z), np.where(z > 0, np.inf, 0.0), z / rays[..., 2])
        region = far_region(range_m, field, scenario.capsule.camera.far,
                            lens=lens)
        assert (far.point.z == 1.0) == region.visible
        np.testing.assert_allclose([far.point.x, far.point.y], region.pixel, atol=0.05)
        seen += region.visible
    assert seen >= 1


@pytest.mark.slow
def test_imu_frame_sees_gravity_up(recorded):
    # At rest the accelerometer reads the reaction to gravity, world +z: its samples taken
    # to world through the capsule's /tf and the IMU's /tf_static (turned 90 degrees on the
    # board) average to (0, 0, g) over the run's last 0.3 s; the AHRS's orientation of the
    # IMU frame agrees with the same chain.
    _, (_, _, messages) = recorded
    X_BS = static_transform(messages, "capsule_imu")
    assert abs(abs(X_BS.rotation().ToQuaternion().z()) - np.sqrt(0.5)) < 1e-12
    capsule = transforms(messages, "capsule")
    world, angles = [], []
    for _, imu, _, _ in messages["/capsule/imu/data"]:
        t = round(seconds(imu.header.stamp), 6)
        if t < 0.7 or t not in capsule:
            continue
        R_WS = pose(*capsule[t]).multiply(X_BS).rotation()
        a = imu.linear_acceleration
        world.append(R_WS.matrix() @ [a.x, a.y, a.z])
        o = imu.orientation
        R_est = Quaternion(o.w, o.x, o.y, o.z).rotation()
        up_est, up = R_est.T @ [0.0, 0.0, 1.0], R_WS.matrix().T @ [0.0, 0.0, 1.0]
        angles.append((np.degrees(np.arccos(np.clip(up_est @ up, -1.0, 1.0))),
                       np.degrees(np.arccos(np.clip(
                           (np.trace(R_est.T @ R_WS.matrix()) - 1.0) / 2.0, -1.0, 1.0)))))
    np.testing.assert_allclose(np.mean(world, axis=0), [0.0, 0.0, 9.81], atol=0.5)
    # The AHRS lost some 9 degrees integrating the gyro clipped at its 250 deg/s range while
    # the capsule first snapped onto the wall; its tilt recovers over seconds (kp = 1 rad/s),
    # its heading never. A frame composed wrongly would be off by the board's 90 degrees.
    tilt, total = np.max(angles, axis=0)
    print(f"AHRS vs tf: tilt {tilt:.2f} deg, whole rotation {total:.2f} deg")
    assert tilt < 10.0 and total < 20.0


@pytest.mark.slow
def test_interrupted_run_leaves_a_finished_file_without_camera_topics(tmp_path):
    # Default with an IMU and the Hall array (no camera), Ctrl-C at 0.3 s inside the
    # simulation: the run's close hook finishes the file, which reads back whole, with the
    # IMU and Hall topics, the tf (at every plant step, so that each Hall sample's stamp
    # has the state it saw) and no camera topic.
    scenario = load_scenario(name="Default", override=[
        "{duration: 1.0, capsule: {imu: {}, magnetic_array: {}, localizer: {}}, "
        f"outputs: {{log_period: {PLANT_STEP}}}}}"])
    assert scenario.plant.time_step == PLANT_STEP
    path = tmp_path / "interrupted.mcap"

    class CtrlC(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclarePeriodicPublishEvent(0.3, 0.3, self._press)

        def _press(self, context):
            raise KeyboardInterrupt

    def interrupt(builder, station):
        builder.AddSystem(CtrlC())

    result = simulate(scenario, progress=False, extend=chain_extends(
        lambda builder, station: add_mcap_logger(builder, station, scenario, path).close,
        interrupt))
    assert result.status == "interrupted"
    header, summary, messages = read_mcap(path)
    assert summary is not None and summary.statistics.message_count > 0  # the footer's index
    assert not any("camera" in topic or "lumen" in topic for topic in messages)
    assert len(messages["/capsule/imu/data"]) >= 29
    imu = messages["/capsule/imu/data"][0][1]
    assert imu.orientation_covariance[0] == -1.0  # no AHRS: no orientation
    last = max(t for items in messages.values() for t, _, _, _ in items)
    assert 0.29e9 <= last <= 0.3e9 + 1e6
    # The Hall sensors' frames: each reading, taken to world by /tf and /tf_static, is the
    # EPM's dipole field at the sensor (within the array's calibration residuals and noise).
    capsule, epm = transforms(messages, "capsule"), transforms(messages, "epm")
    moment = scenario.epm.magnet.moment()
    for i in range(4):
        X_BS = static_transform(messages, f"capsule_hall_{i}")
        for _, field, _, _ in messages[f"/capsule/magnetic_array/hall_{i}"][-5:]:
            t = round(seconds(field.header.stamp), 6)
            X_WS = pose(*capsule[t]).multiply(X_BS)
            X_WE = pose(*epm[t])
            expected = dipole_field(moment * X_WE.rotation().col(2),
                                    X_WS.translation() - X_WE.translation())
            B = field.magnetic_field
            measured = X_WS.rotation().matrix() @ [B.x, B.y, B.z]
            assert np.linalg.norm(measured - expected) < 0.02 * np.linalg.norm(expected) + 2e-4
    estimate = messages["/capsule/localizer/pose"][-1][1]
    assert estimate.header.frame_id == "world" and len(estimate.pose.covariance) == 36
    # Each estimate (made half a period after the samples, on them) is stamped as they are.
    hall = [seconds(m.header.stamp) for _, m, _, _ in messages["/capsule/magnetic_array/hall_0"]]
    poses = [seconds(m.header.stamp) for _, m, _, _ in messages["/capsule/localizer/pose"]]
    assert len(poses) >= 29 and poses == hall[:len(poses)]
    assert hall[0] == pytest.approx(PLANT_STEP, abs=1e-9)


class _FailingWriter:
    """An mcap Writer whose start (or finish) raises, keeping the stream it was given."""

    streams = []

    def __init__(self, stream, **kwargs):
        self.streams.append(stream)

    def start(self, **kwargs):
        raise OSError(28, "No space left on device")


class _WriterFailingAtFinish(mcap_file.Writer):
    def finish(self):
        raise OSError(5, "Input/output error")


def test_the_file_is_closed_on_every_path(tmp_path):
    # Writer.start raising (disk full at the header): the stream opened for it is closed.
    log = Ros2McapFile(tmp_path / "a.mcap")
    tf = {"transforms": []}
    with mock.patch.object(mcap_file, "Writer", _FailingWriter):
        with pytest.raises(OSError, match="No space"):
            log.write("/tf", "tf2_msgs/msg/TFMessage", tf, 0)
    stream, = _FailingWriter.streams
    assert stream.closed
    log.close()
    log.close()  # idempotent
    # Writer.finish raising: the file is closed all the same, and the error comes out once.
    log = Ros2McapFile(tmp_path / "b.mcap")
    with mock.patch.object(mcap_file, "Writer", _WriterFailingAtFinish):
        log.write("/tf", "tf2_msgs/msg/TFMessage", tf, 0)
    stream = log._stream
    with pytest.raises(OSError, match="Input/output"):
        log.close()
    assert stream.closed
    log.close()
    # The ordinary path: closed twice, the file reads back whole.
    log = Ros2McapFile(tmp_path / "c.mcap")
    log.write("/tf", "tf2_msgs/msg/TFMessage", tf, 5)
    log.close()
    log.close()
    _, summary, messages = read_mcap(tmp_path / "c.mcap")
    assert summary.statistics.message_count == 1 and messages["/tf"][0][0] == 5
    with pytest.raises(RuntimeError, match="closed"):
        log.write("/tf", "tf2_msgs/msg/TFMessage", tf, 6)


@pytest.mark.slow
def test_the_wall_pressure_maps_are_images_of_the_runs_map(tmp_path):
    # `run --mcap` for 2 s of Default: the map of the wall's pressure every second, three
    # 32FC1 images of the colon unrolled (a pixel a patch: rows around, columns along) that
    # an independent CDR implementation decodes and encodes again byte for byte; the last
    # ones are the run's wall_pressure.npz (the run ends at that second), stamped with the
    # state of its last sample: one the capsule's /tf has.
    path, out = tmp_path / "run.mcap", tmp_path / "run"
    code = cli_main(["run", "--duration", "2.0", "--quiet", "--no-recording", "--out",
                     str(out), "--mcap", str(path)])
    assert code == 0
    _, summary, messages = read_mcap(path)
    tf_stamps = transforms(messages, "capsule")
    with np.load(out / "wall_pressure.npz") as data:
        saved = {key: data[key] for key in data.files}
    shape = (len(saved["theta_edges_deg"]) - 1, len(saved["s_edges_m"]) - 1)
    for topic, key in (("/capsule/contact/wall_pressure/peak", "peak_pressure_kPa"),
                       ("/capsule/contact/wall_pressure/above_injury", "longest_above_injury_s"),
                       ("/capsule/contact/wall_pressure/above_ischaemia",
                        "longest_above_ischaemia_s")):
        items = messages[topic]
        assert [t for t, _, _, _ in items] == [1_000_000_000, 2_000_000_000], topic
        _, image, raw, name = items[-1]
        assert name == "sensor_msgs/msg/Image" and image.encoding == "32FC1"
        assert image.header.frame_id == "colon_wall_map"
        assert (image.height, image.width, image.step) == (*shape, 4 * shape[1])
        values = np.frombuffer(bytes(image.data), dtype="<f4").reshape(shape)
        np.testing.assert_allclose(values.T, saved[key], rtol=1e-6, atol=1e-9)
        assert round(seconds(image.header.stamp), 6) in tf_stamps
        assert seconds(image.header.stamp) == pytest.approx(float(saved["last_time_s"]),
                                                            abs=0.0021)
        again = HUMBLE.serialize_cdr(HUMBLE.deserialize_cdr(raw, name), name)
        assert bytes(again) == raw
    assert saved["peak_pressure_kPa"].max() > 4.0   # the capsule rests on the wall
