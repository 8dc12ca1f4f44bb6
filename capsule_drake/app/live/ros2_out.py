"""The run's channels as ROS 2 topics over DDS (Cyclone DDS's Python binding, no ROS
installation), and the EPM commanded from a ROS 2 topic.

A ROS 2 machine on the same network (the same domain id; Cyclone DDS, or any RMW that
speaks DDS with ROS 2's names) sees each channel of app/channels.py as the topic of that
name and type: DDS topic `rt/<topic>`, type `pkg::msg::dds_::Type_` (app/live/dds_types.py),
XCDR1 as ROS 2 exchanges, QoS as a ROS 2 publisher's defaults (reliable, keep last 10,
volatile; latched channels transient-local, keep last 1, as /tf_static).

`EpmGoalSubscriber` reads geometry_msgs/PoseStamped goals on `/epm/goal` (world frame: the
magnet's centre, its moment along the pose's z axis) and gives the latest as the EPM's
command; the station's EPM guard then keeps its clearance, as for every driver. Before the
first goal, or after `hold_after` seconds without one (a lost link), the command is NaN:
the guard holds the EPM where it is.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from cyclonedds.core import Listener, Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from capsule_drake.app.channels import COMMAND_CHANNELS
from capsule_drake.app.live.dds_types import dds_topic_name, from_idl, idl_type, to_idl

# Only this machine (the loopback, no multicast, the peer at 127.0.0.1), unless told
# otherwise: a run's topics are not sent onto a network nobody asked it to use.
LOOPBACK_CONFIG = (
    '<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/>'
    "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><Peers>"
    '<Peer address="127.0.0.1"/></Peers><ParticipantIndex>auto</ParticipantIndex>'
    "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex></Discovery></Domain></CycloneDDS>")


def _qos(latched: bool) -> Qos:
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
    if loopback:
        from cyclonedds.domain import Domain
        domain = Domain(domain_id, LOOPBACK_CONFIG)
        return DomainParticipant(domain_id), domain
    return DomainParticipant(domain_id), None


class Ros2Topics:
    """Publishes the channels given to `publish` as ROS 2 topics (module docstring)."""

    fatal = False

    def __init__(self, domain_id: int = 0, loopback: bool = True):
        self.domain_id = domain_id
        self.loopback = loopback
        self._participant, self._domain = participant(domain_id, loopback)
        self._writers: dict[str, DataWriter] = {}
        self.messages = 0

    @property
    def name(self) -> str:
        return f"the ROS 2 topics (DDS domain {self.domain_id})"

    @property
    def dds_participant(self) -> DomainParticipant:
        return self._participant

    def _writer(self, topic: str, spec) -> DataWriter:
        dds_topic = Topic(self._participant, dds_topic_name(topic), idl_type(spec.type_name))
        writer = DataWriter(self._participant, dds_topic, qos=_qos(spec.latched))
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


class GoalInbox:
    """The latest goal received on a ROS 2 topic, kept by a DDS listener thread; `command()`
    gives it (NaN before the first, or `hold_after` seconds after the last: the EPM holds).
    Malformed goals are counted and give NaN (hold), never an exception in the run."""

    def __init__(self, domain_id: int = 0, loopback: bool = True, hold_after: float = 0.5,
                 topic: str = COMMAND_CHANNELS[0].topic, clock=time.monotonic,
                 dds_participant=None):
        spec = next(c for c in COMMAND_CHANNELS if c.topic == topic)
        self._type = spec.type_name
        self._lock = threading.Lock()
        self._latest = np.full(6, np.nan)
        self._received_at = None
        self._clock = clock
        self.hold_after = hold_after
        self.received = 0
        self.malformed = 0
        if dds_participant is None:
            dds_participant, self._domain = participant(domain_id, loopback)
        self._participant = dds_participant
        dds_topic = Topic(dds_participant, dds_topic_name(topic), idl_type(self._type))
        self._reader = DataReader(dds_participant, dds_topic, qos=_qos(False),
                                  listener=Listener(on_data_available=self._on_data))

    def _on_data(self, reader) -> None:
        for sample in reader.take(N=16):
            try:
                command = goal_command(from_idl(sample))
            except Exception:
                command = np.full(6, np.nan)
            with self._lock:
                self.received += 1
                if not np.all(np.isfinite(command)):
                    self.malformed += 1
                self._latest = command
                self._received_at = self._clock()

    def command(self) -> np.ndarray:
        with self._lock:
            if self._received_at is None or self._clock() - self._received_at > self.hold_after:
                return np.full(6, np.nan)
            return self._latest.copy()
