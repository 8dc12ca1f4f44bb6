"""The run's live outputs: one table of channels for the MCAP file, Foxglove and ROS 2; a
Foxglove client made of Foxglove's own packages decoding every channel of a running
simulation; Cyclone DDS's own command line receiving the ROS 2 topics; the EPM driven from
a ROS 2 goal topic through the clearance; the output flags as settings; pacing."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2._dynamic import serialize_dynamic

from capsule_drake.app.channels import CHANNELS, ChannelWriter, channel_of
from capsule_drake.app.live.dds_types import dds_topic_name, dds_type_name, idl_type, to_idl
from capsule_drake.app.live.pacing import PaceWatch
from capsule_drake.app.live.ros2_out import LOOPBACK_CONFIG, goal_command, twist_command
from capsule_drake.app.log_spool import load_logs
from capsule_drake.app.ros2_messages import DEFINITIONS, header, schema_text, vector3
from capsule_drake.app.scene_markers import scene_markers

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "tests" / "foxglove_client"
ON_CI = bool(os.environ.get("CI"))


def _encode(type_name, message):
    return bytes(serialize_dynamic(type_name, schema_text(type_name))[type_name](message))


SAMPLES = {
    "sensor_msgs/msg/Imu": {"header": header(1_500_000_000, "capsule_imu"),
                            "orientation": {"x": 0.1, "y": 0.2, "z": 0.3, "w": 0.9},
                            "orientation_covariance": [-1.0] + [0.0] * 8,
                            "angular_velocity": vector3([1, 2, 3]),
                            "angular_velocity_covariance": [0.1] * 9,
                            "linear_acceleration": vector3([4, 5, 6])},
    "sensor_msgs/msg/Image": {"header": header(3, "cam"), "height": 2, "width": 3,
                              "encoding": "rgb8", "is_bigendian": 0, "step": 9,
                              "data": bytes(range(18))},
    "sensor_msgs/msg/CameraInfo": {"header": header(7, "cam"), "height": 4, "width": 5,
                                   "distortion_model": "equidistant", "d": [0.1, 0.2, 0.3, 0.4],
                                   "k": [1.0] * 9, "r": [0.5] * 9, "p": [2.0] * 12},
    "tf2_msgs/msg/TFMessage": {"transforms": [{
        "header": header(5, "world"), "child_frame_id": "capsule",
        "transform": {"translation": vector3([1, 2, 3]),
                      "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]},
    "visualization_msgs/msg/MarkerArray": scene_markers(
        np.arange(18, dtype=float).reshape(2, 3, 3), 0.0055, 0.02, 0.1, 0.1),
    "geometry_msgs/msg/PoseStamped": {"header": header(0, "world"), "pose": {
        "position": vector3([0.1, 0.2, 0.3]),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}},
}


@pytest.mark.parametrize("type_name", sorted(SAMPLES))
def test_dds_samples_are_the_mcap_files_bytes(type_name):
    """The DDS types made from the field lists encode (Cyclone DDS's own serialiser, XCDR1
    as ROS 2) byte for byte as the MCAP writer's encoder (mcap_ros2) does: two encoders of
    the same definitions agree, so a ROS 2 node decodes the topics as a reader the file."""
    message = SAMPLES[type_name]
    assert to_idl(type_name, message).serialize() == _encode(type_name, message)
    assert dds_type_name(type_name).endswith("::dds_::" + type_name.split("/")[-1] + "_")


def test_every_definition_makes_a_dds_type():
    for type_name in DEFINITIONS:
        assert idl_type(type_name).__name__.endswith("_")
    assert dds_topic_name("/capsule/imu/data") == "rt/capsule/imu/data"


def test_the_channel_table_names_known_types_and_each_topic_once():
    topics = [spec.topic for spec in CHANNELS]
    assert len(topics) == len(set(topics))
    for spec in CHANNELS:
        assert spec.type_name in DEFINITIONS, spec
    assert channel_of("/capsule/magnetic_array/hall_3").type_name == \
        "sensor_msgs/msg/MagneticField"
    with pytest.raises(KeyError, match="/capsule/nothing"):
        channel_of("/capsule/nothing")


class _Sink:
    def __init__(self, fatal, fail=False):
        self.fatal, self.fail, self.name = fatal, fail, f"sink fatal={fatal}"
        self.got, self.closed = [], False

    def publish(self, topic, spec, message, data, log_time_ns):
        if self.fail:
            raise ConnectionError("peer went away")
        self.got.append((topic, data))

    def close(self):
        self.closed = True


def test_the_writer_encodes_once_for_every_output_and_drops_a_failing_live_one(capsys):
    good, broken, mcap = _Sink(False), _Sink(False, fail=True), _Sink(True)
    writer = ChannelWriter([good, broken, mcap])
    message = SAMPLES["sensor_msgs/msg/Imu"]
    writer.write("/capsule/imu/data", "sensor_msgs/msg/Imu", message, 0)
    writer.write("/capsule/imu/data", "sensor_msgs/msg/Imu", message, 1)
    assert good.got == mcap.got == [("/capsule/imu/data", _encode("sensor_msgs/msg/Imu",
                                                                  message))] * 2
    assert broken not in writer.sinks and broken.closed
    assert "peer went away" in capsys.readouterr().err and len(writer.dropped) == 1
    assert writer.log is mcap
    with pytest.raises(ValueError, match="channel table says"):
        writer.write("/capsule/imu/data", "sensor_msgs/msg/MagneticField", {}, 2)
    with pytest.raises(KeyError):
        writer.write("/not/a/channel", "sensor_msgs/msg/Imu", message, 2)
    mcap.fail = True    # a fatal output's failure reaches the run (which stops and says so)
    with pytest.raises(ConnectionError):
        writer.write("/capsule/imu/data", "sensor_msgs/msg/Imu", message, 3)


def test_the_run_declares_its_topics_and_the_foxglove_server_has_them_before_it_listens():
    """A channel advertised to a viewer already connected can lose its subscription in
    foxglove-sdk, so the server makes every declared channel before it listens; a topic
    written but not declared is an error, so a stream's `topics` cannot fall behind what it
    writes."""
    from capsule_drake.app.live.foxglove_out import FoxgloveLive
    live = FoxgloveLive(port=0)
    writer = ChannelWriter([live])
    with pytest.raises(KeyError):
        writer.declare(["/not/a/channel"])
    writer.declare(["/tf_static", "/capsule/imu/data"])
    assert live.server is None and set(live._channels) == {"/tf_static", "/capsule/imu/data"}
    live.start()
    try:
        assert live.port > 0
        writer.write("/capsule/imu/data", "sensor_msgs/msg/Imu", SAMPLES["sensor_msgs/msg/Imu"], 0)
        with pytest.raises(ValueError, match="not among the topics declared"):
            writer.write("/tf", "tf2_msgs/msg/TFMessage", SAMPLES["tf2_msgs/msg/TFMessage"], 0)
    finally:
        writer.close()


def test_a_goal_pose_is_its_position_and_z_axis_and_a_bad_one_holds():
    s = np.sqrt(0.5)   # 90 degrees about x: z goes to -y
    goal = {"pose": {"position": vector3([0.1, 0.2, 0.3]),
                     "orientation": {"x": s, "y": 0.0, "z": 0.0, "w": s}}}
    np.testing.assert_allclose(goal_command(goal), [0.1, 0.2, 0.3, 0.0, -1.0, 0.0], atol=1e-12)
    for bad in ({"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}, {"x": np.nan, "y": 0, "z": 0, "w": 1}):
        assert np.all(np.isnan(goal_command({"pose": {"position": vector3([0, 0, 0]),
                                                      "orientation": bad}})))


class _Inbox:
    def __init__(self):
        self.message = (None, np.full(6, np.nan))

    def latest(self):
        return self.message


def test_the_command_topics_make_the_epm_command_a_goal_a_velocity_or_a_hold():
    """EpmGoalSource: nothing received holds (NaN); a velocity moves the EPM's pose by v t
    and turns its moment at w (checked against the closed form of a constant twist); a goal
    is the command; a lost link holds again, and a velocity after it goes on from the
    last command."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource
    from capsule_drake.app.live.outputs import EpmGoalSource
    inbox = _Inbox()
    builder = DiagramBuilder()
    source = builder.AddSystem(EpmGoalSource(inbox, period=0.01))
    start = np.array([0.1, 0.0, 0.3, 1.0, 0.0, 0.0])
    pose = builder.AddSystem(ConstantVectorSource(start))
    builder.Connect(pose.get_output_port(), source.GetInputPort("epm_pose"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = source.GetMyContextFromRoot(simulator.get_mutable_context())
    command = lambda: source.GetOutputPort("epm_command").Eval(context)   # noqa: E731
    simulator.AdvanceTo(0.05)
    assert np.all(np.isnan(command()))
    w = 0.5   # rad/s about z: the moment turns from x toward y
    inbox.message = ("velocity", np.array([0.0, 0.02, 0.0, 0.0, 0.0, w]))
    simulator.AdvanceTo(1.0)
    steps = round((1.0 - 0.05) / 0.01)   # updates at 0.06 ... 1.0 s
    now = command()
    np.testing.assert_allclose(now[:3], start[:3] + [0.0, 0.02 * steps * 0.01, 0.0], atol=1e-9)
    angle = np.arctan2(now[4], now[3])
    assert angle == pytest.approx(w * steps * 0.01, rel=2e-3)   # explicit steps: O(dt)
    inbox.message = ("goal", np.array([0.0, 0.1, 0.35, 0.0, 0.0, 1.0]))
    simulator.AdvanceTo(1.1)
    np.testing.assert_allclose(command(), [0.0, 0.1, 0.35, 0.0, 0.0, 1.0])
    inbox.message = (None, np.full(6, np.nan))   # the link is lost
    simulator.AdvanceTo(1.2)
    assert np.all(np.isnan(command()))
    inbox.message = ("velocity", np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]))
    simulator.AdvanceTo(1.3)
    np.testing.assert_allclose(command()[:3], [0.01 * 10 * 0.01, 0.1, 0.35], atol=1e-9)


def test_a_twist_is_its_velocities_and_a_bad_one_holds():
    twist = {"twist": {"linear": vector3([1, 2, 3]), "angular": vector3([4, 5, 6])}}
    np.testing.assert_array_equal(twist_command(twist), [1, 2, 3, 4, 5, 6])
    twist["twist"]["linear"]["y"] = np.inf
    assert np.all(np.isnan(twist_command(twist)))


def test_the_pace_watch_says_when_a_run_falls_behind_and_when_it_is_back():
    clock = iter(np.arange(0.0, 100.0, 1.0))
    lines = []
    watch = PaceWatch(1.0, window=5.0, clock=lambda: next(clock), stream=sys.stdout)
    watch._say = lines.append
    sim = 0.0
    for k in range(30):
        sim += 0.5 if k < 15 else 1.0   # half real time, then real time
        watch.update(sim)
    assert len(lines) == 2 and "cannot keep the pace" in lines[0] and "back at pace" in lines[1]
    assert watch.slowest == pytest.approx(0.5)


def test_the_output_flags_are_spellings_of_the_scenarios_outputs(tmp_path):
    from capsule_drake.app.cli_parser import _parser
    from capsule_drake.app.commands.common import _load
    args = _parser().parse_args(["run", "--mcap", str(tmp_path / "a.mcap"), "--foxglove",
                                 "--ros2", "3", "--no-recording", "--meshcat",
                                 "--port", "7123"])
    outputs = _load(args).outputs
    assert outputs.mcap.path == str(tmp_path / "a.mcap") and not outputs.recording
    assert (outputs.foxglove.host, outputs.foxglove.port) == ("127.0.0.1", 8765)
    assert (outputs.ros2.domain_id, outputs.ros2.loopback) == (3, True)
    assert outputs.meshcat.port == 7123 and outputs.live()
    plain = _load(_parser().parse_args(["run"])).outputs
    assert plain.mcap is None and plain.recording and not plain.live()
    # The MCAP output as the run makes it (its file is created at its first message).
    from mcap.writer import CompressionType
    from capsule_drake.app.live.outputs import channel_sinks
    text = "{outputs: {mcap: {path: " + str(tmp_path / "b.mcap") + ", compression: lz4}}}"
    sink, = channel_sinks(_load(_parser().parse_args(["run", "--scenario-text", text])).outputs)
    assert sink.fatal and sink._compression == CompressionType.LZ4
    assert not (tmp_path / "b.mcap").exists()


# --- Live, against other people's clients ----------------------------------------------------

def _node_client() -> Path:
    """The Foxglove client's packages (tests/foxglove_client, pinned in its lock file),
    installed with npm once."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        if ON_CI:
            pytest.fail("node and npm are needed for the Foxglove client test")
        pytest.skip("node and npm are not installed")
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--silent"], cwd=CLIENT,
                       check=True, timeout=600)
    return CLIENT / "client.mjs"


def _start_run(args, out: Path):
    command = [sys.executable, "-m", "capsule_drake.app", "run", *args, "--no-recording",
               "--quiet", "--out", str(out)]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, cwd=ROOT)


def _wait_for_line(process, pattern: str, timeout: float = 300.0) -> re.Match:
    deadline = time.monotonic() + timeout
    seen = []
    for line in process.stdout:
        seen.append(line)
        match = re.search(pattern, line)
        if match:
            return match
        if time.monotonic() > deadline:
            break
    process.kill()
    raise AssertionError(f"no line matching {pattern!r}; the run said:\n{''.join(seen)}")


LIVE_TOPICS = ["/tf", "/tf_static", "/scene/markers", "/capsule/camera/image_raw",
               "/capsule/camera/camera_info", "/capsule/imu/data", "/capsule/magnetometer",
               "/capsule/contact/wrench", "/capsule/contact/peak_pressure",
               "/capsule/lumen_truth/pixel", "/capsule/lumen_truth/point",
               "/capsule/lumen_tracker/pixel"]


@pytest.mark.slow
def test_a_foxglove_client_decodes_every_channel_of_a_running_simulation(tmp_path):
    """A run with the Foxglove output (its port any free one, waiting for a viewer), and a
    client made of Foxglove's own packages (@foxglove/ws-protocol, rosmsg,
    rosmsg2-serialization) under node: it subscribes to every channel the server
    advertises and decodes a message of each with the advertised schema; the scene holds
    the colon's wall, the capsule and the EPM."""
    client = _node_client()
    # On a loaded machine the client falls behind the stream, and the server drops its
    # oldest queued messages past `backlog` (1024 by default; this scenario sends about
    # 615 a simulated second; once, in CI, no camera image reached the client). The test asks whether each
    # channel decodes, not how fast a starved viewer reads, so it queues the whole run.
    run = _start_run(["--scenario", "WithSensors", "--duration", "6", "--foxglove", "0",
                      "--scenario-text",
                      "{outputs: {foxglove: {wait_for_client: 120, backlog: 200000}}}"],
                     tmp_path / "run")
    port = _wait_for_line(run, r"ws://127\.0\.0\.1:(\d+)").group(1)
    viewer = subprocess.run(["node", str(client), f"ws://127.0.0.1:{port}", "240",
                             *LIVE_TOPICS], capture_output=True, text=True, timeout=300)
    rest, _ = run.communicate(timeout=600)
    assert run.returncode == 0, rest
    seen = json.loads(viewer.stdout)
    assert seen["errors"] == [], seen["errors"]
    assert viewer.returncode == 0, ("advertised, none decoded:",
                                    set(seen["advertised"]) - set(seen["decoded"]),
                                    {t: e["count"] for t, e in seen["decoded"].items()})
    decoded = seen["decoded"]
    assert set(LIVE_TOPICS) <= set(decoded), sorted(set(LIVE_TOPICS) - set(decoded))
    for topic, entry in decoded.items():
        assert entry["schema"] == channel_of(topic).type_name
    image = decoded["/capsule/camera/image_raw"]["first"]
    assert image["encoding"] == "rgb8" and image["width"] > 0
    markers = {(m["ns"], m["type"]): m for m in decoded["/scene/markers"]["first"]["markers"]}
    wall = markers[("colon_wall", 11)]
    assert wall["header"]["frame_id"] == "world" and int(wall["points"][1:].split()[0]) > 3000
    assert ("capsule", 3) in markers and ("epm", 3) in markers
    assert markers[("capsule", 3)]["frame_locked"] and markers[("capsule", 3)]["header"][
        "frame_id"] == "capsule"


def _cyclonedds_cli() -> str:
    path = Path(sys.executable).parent / "cyclonedds"
    assert path.is_file(), "cyclonedds's command line comes with the cyclonedds package"
    return str(path)


@pytest.mark.slow
def test_ros2_topics_reach_cyclone_dds_and_a_goal_moves_the_epm_held_at_the_clearance(
        tmp_path):
    """A run with ROS 2 topics (its own DDS domain, the loopback) and the EPM on the goal
    topic: Cyclone DDS's command line, which discovers the types over XTypes, receives the
    image, IMU and tf topics under ROS 2's names and types; a goal published on /epm/goal
    under the skin moves the EPM over it and the guard holds it at the clearance."""
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from capsule_drake.app.live.ros2_out import participant
    domain = 40 + os.getpid() % 150
    env = dict(os.environ, CYCLONEDDS_URI=LOOPBACK_CONFIG)
    out = tmp_path / "run"
    run = _start_run(["--scenario", "WithSensors", "--duration", "8", "--ros2", str(domain),
                      "--scenario-text",
                      # a small image: the command line prints each of its bytes
                      "{epm: {driver: !External {}}, outputs: {ros2: {epm_command: true}}, "
                      "capsule: {camera: {lens: {width: 24, height: 24}}}}"], out)
    _wait_for_line(run, r"live: the ROS 2 topics")
    topics = {"/tf": "TFMessage_(", "/capsule/imu/data": "Imu_(",
              "/capsule/camera/image_raw": "Image_("}
    # The run's writers appear with their first messages, after its build: the command line
    # scans for a topic's type only for a while, so it is started once a reader here has had
    # a sample of each of the three.
    dds, keep = participant(domain, loopback=True)
    types = {"/tf": "tf2_msgs/msg/TFMessage", "/capsule/imu/data": "sensor_msgs/msg/Imu",
             "/capsule/camera/image_raw": "sensor_msgs/msg/Image"}
    readers = {t: DataReader(dds, Topic(dds, dds_topic_name(t), idl_type(types[t])))
               for t in topics}
    waiting, deadline = set(topics), time.monotonic() + 300
    while waiting:
        assert time.monotonic() < deadline and run.poll() is None, sorted(waiting)
        waiting -= {t for t in waiting if readers[t].take(N=10)}
        time.sleep(0.2)
    listeners = {topic: subprocess.Popen(
        [_cyclonedds_cli(), "subscribe", dds_topic_name(topic), "-i", str(domain), "-r", "5s",
         "--suppress-progress-bar", "--qos", "scan-random", "--color", "none"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        for topic in topics}
    writer = DataWriter(dds, Topic(dds, "rt/epm/goal", idl_type("geometry_msgs/msg/PoseStamped")))
    goal = {"header": header(0, "world"), "pose": {           # 5 cm off, below the skin
        "position": vector3([0.05, 0.0, 0.0]), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0,
                                                               "w": 1.0}}}
    while run.poll() is None:
        writer.write(to_idl("geometry_msgs/msg/PoseStamped", goal))
        time.sleep(0.05)
    said = run.stdout.read()
    heard = {}
    for topic, listener in listeners.items():
        listener.send_signal(signal.SIGINT)
        heard[topic] = listener.communicate(timeout=60)[0]
    assert run.returncode == 0, said
    for topic, type_text in topics.items():
        assert type_text in heard[topic], (topic, heard[topic][-2000:])
    assert "frame_id='capsule_camera_optical_frame'" in heard["/capsule/camera/image_raw"]
    metrics = json.loads((out / "metrics.json").read_text())
    epm = load_logs(out)["epm_pose"]
    np.testing.assert_allclose(epm[:2, -1], [0.05, 0.0], atol=1e-3)   # over the goal
    assert metrics["min_epm_skin_gap_m"] == pytest.approx(0.02, abs=2e-3)  # at the clearance
