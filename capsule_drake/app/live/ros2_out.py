"""The run's channels as ROS 2 topics over DDS (Cyclone DDS's Python binding, no ROS
installation), and the EPM commanded from a ROS 2 topic.

A ROS 2 machine on the same network (the same domain id; Cyclone DDS, or any RMW that
speaks DDS with ROS 2's names) sees each channel of app/channels.py as the topic of that
name and type: DDS topic `rt/<topic>`, type `pkg::msg::dds_::Type_` (app/live/dds_types.py),
XCDR1 as ROS 2 exchanges, QoS as a ROS 2 publisher's defaults (reliable, keep last 10,
volatile; latched channels transient-local, keep last 1, as /tf_static).

`GoalInbox` reads geometry_msgs/PoseStamped goals on `/epm/goal` (world frame: the magnet's
centre, its moment along the pose's z axis) and geometry_msgs/TwistStamped velocities on
`/epm/velocity` (world frame: the centre's velocity, the moment's turn), keeping the latest
of each; app/live/outputs.py's EpmGoalSource makes the EPM's command of them (a goal is
the command, a velocity moves the last command); the station's EPM guard then keeps its
clearance, as for every driver. Before the first message, or after `hold_after` seconds
without one (a lost link), the command is NaN: the guard holds the EPM where it is.
"""

from __future__ import annotations

import threading
import time

import types

import numpy as np

from capsule_drake.app.channels import COMMAND_CHANNELS
from capsule_drake.app.live.dds_types import dds_topic_name, from_idl, idl_type, to_idl

# Only this machine (the loopback, no multicast, the peer at 127.0.0.1), unless told
# otherwise: a run's topics are not sent onto a network nobody asked it to use.
LOOPBACK_CONFIG = (
    '<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/>'
    "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><Peers>"
    '<Peer address="127.0.0.1"/></Peers><ParticipantIndex>auto</ParticipantIndex>'
    "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex></Discovery></Domain></CycloneDDS>")


def _dds() -> types.SimpleNamespace:
    """Cyclone DDS's Python binding, imported at the first use (a run without ROS 2 topics
    does not load it)."""
    from cyclonedds.core import Listener, Policy, Qos
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    return types.SimpleNamespace(Listener=Listener, Policy=Policy, Qos=Qos, Domain=Domain,
                                 DomainParticipant=DomainParticipant, DataWriter=DataWriter,
                                 DataReader=DataReader, Topic=Topic, duration=duration)


def _qos(latched: bool):
    dds = _dds()
    Policy, Qos, duration = dds.Policy, dds.Qos, dds.duration
    policies = [Policy.Reliability.Reliable(duration(seconds=1)),
                Policy.DataRepresentation(use_cdrv0_representation=True)]
    if latched:
        policies += [Policy.Durability.TransientLocal, Policy.History.KeepLast(1)]
    else:
        policies += [Policy.Durability.Volatile, Policy.History.KeepLast(10)]
    return Qos(*policies)


def participant(domain_id: int = 0, loopback: bool = True):
    """(participant, domain): a DDS participant on `domain_id`, on the loopback only unless
    `loopback` is False (then Cyclone DDS's own configuration: $CYCLONEDDS_URI, or all
    interfaces); keep the domain (None then) as long as the participant."""
    dds = _dds()
    if loopback:
        domain = dds.Domain(domain_id, LOOPBACK_CONFIG)
        return dds.DomainParticipant(domain_id), domain
    return dds.DomainParticipant(domain_id), None


class Ros2Topics:
    """Publishes the channels given to `publish` as ROS 2 topics (module docstring)."""

    fatal = False

    def __init__(self, domain_id: int = 0, loopback: bool = True):
        self.domain_id = domain_id
        self.loopback = loopback
        self._participant, self._domain = participant(domain_id, loopback)
        self._writers: dict = {}
        self.messages = 0

    @property
    def name(self) -> str:
        return f"the ROS 2 topics (DDS domain {self.domain_id})"

    @property
    def dds_participant(self):
        return self._participant

    def _writer(self, topic: str, spec):
        dds = _dds()
        dds_topic = dds.Topic(self._participant, dds_topic_name(topic),
                              idl_type(spec.type_name))
        writer = dds.DataWriter(self._participant, dds_topic, qos=_qos(spec.latched))
        self._writers[topic] = writer
        return writer

    def publish(self, topic: str, spec, message: dict, data: bytes, log_time_ns: int) -> None:
        writer = self._writers.get(topic) or self._writer(topic, spec)
        writer.write(to_idl(spec.type_name, message))
        self.messages += 1

    def close(self) -> None:
        self._writers.clear()
        self._participant = None
        self._domain = None


def goal_command(message: dict) -> np.ndarray:
    """[p (3), m_hat (3)] of a PoseStamped goal: its position and its z axis; NaN (hold)
    for a goal that is not finite or whose orientation is not a rotation (a zero
    quaternion)."""
    pose = message["pose"]
    p = np.array([pose["position"][k] for k in "xyz"], dtype=float)
    q = np.array([pose["orientation"][k] for k in "wxyz"], dtype=float)
    norm = np.linalg.norm(q)
    if not (np.all(np.isfinite(p)) and np.isfinite(norm) and norm > 1e-6):
        return np.full(6, np.nan)
    w, x, y, z = q / norm
    axis = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    return np.concatenate([p, axis])


def twist_command(message: dict) -> np.ndarray:
    """[v (3), w (3)] of a TwistStamped (world); NaN (hold) when not finite."""
    twist = message["twist"]
    values = np.array([twist["linear"][k] for k in "xyz"] + [twist["angular"][k] for k in "xyz"],
                      dtype=float)
    return values if np.all(np.isfinite(values)) else np.full(6, np.nan)


class GoalInbox:
    """The latest goal and velocity received on the ROS 2 command topics, kept by DDS
    listener threads. `latest()` gives (kind, values): ("goal", [p, m_hat]) or
    ("velocity", [v, w]) for the most recent message, or (None, NaN) before the first, after
    `hold_after` seconds without one (a lost link) or when the last was malformed (each
    counted): the EPM holds. Never an exception in the run."""

    def __init__(self, domain_id: int = 0, loopback: bool = True, hold_after: float = 0.5,
                 clock=time.monotonic, dds_participant=None):
        self._lock = threading.Lock()
        self._latest = (None, np.full(6, np.nan))
        self._received_at = None
        self._clock = clock
        self.hold_after = hold_after
        self.received = 0
        self.malformed = 0
        if dds_participant is None:
            dds_participant, self._domain = participant(domain_id, loopback)
        self._participant = dds_participant
        self._readers = []
        dds = _dds()
        for spec, kind, read in ((COMMAND_CHANNELS[0], "goal", goal_command),
                                 (COMMAND_CHANNELS[1], "velocity", twist_command)):
            dds_topic = dds.Topic(dds_participant, dds_topic_name(spec.topic),
                                  idl_type(spec.type_name))
            self._readers.append(dds.DataReader(
                dds_participant, dds_topic, qos=_qos(False),
                listener=dds.Listener(on_data_available=lambda reader, kind=kind, read=read:
                                  self._on_data(reader, kind, read))))

    def _on_data(self, reader, kind, read) -> None:
        for sample in reader.take(N=16):
            try:
                values = read(from_idl(sample))
            except Exception:
                values = np.full(6, np.nan)
            self.receive(kind, values)

    def receive(self, kind: str, values) -> None:
        """Notes a message (the listener's; a test's)."""
        values = np.asarray(values, dtype=float)
        with self._lock:
            self.received += 1
            if not np.all(np.isfinite(values)):
                self.malformed += 1
            self._latest = (kind, values)
            self._received_at = self._clock()

    def latest(self):
        with self._lock:
            kind, values = self._latest
            if (self._received_at is None or self._clock() - self._received_at > self.hold_after
                    or not np.all(np.isfinite(values))):
                return None, np.full(6, np.nan)
            return kind, values.copy()
