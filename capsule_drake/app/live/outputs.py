"""The scenario's channel outputs connected to a run: the MCAP file, the Foxglove server and
the ROS 2 topics all through one ChannelLogger (app/mcap_log.py), and the EPM's goal topic
into the station's `epm.command` input.

`add_channel_outputs(builder, station, scenario)` adds them beside a station (the Run does,
app/run.py) and returns their ChannelLogger (None when the scenario has none), whose
`close()` closes every output.
"""

from __future__ import annotations

import sys

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.app.live.foxglove_out import FoxgloveLive
from capsule_drake.app.live.ros2_out import GoalInbox, Ros2Topics
from capsule_drake.app.mcap_file import Ros2McapFile
from capsule_drake.app.mcap_log import add_channel_logger


class EpmGoalSource(LeafSystem):
    """The EPM's command from the ROS 2 command topics (app/live/ros2_out.py `GoalInbox`),
    every `period` s: a goal is the command; a velocity moves the last command (from the
    EPM's pose when there is none yet) by v dt and turns its moment by w dt; no message, a
    lost link or a malformed one: NaN, which the EPM's guard turns into a hold (the last
    command is kept for a velocity that comes back).

    .. pydrake_system::

        name: EpmGoalSource
        input_ports:
        - epm_pose
        output_ports:
        - epm_command

    epm_pose: the station's epm.pose [p_WE, m_hat_W]. epm_command: [p_WE, m_hat_W] or NaN.
    The output is the state (no feedthrough from the pose).
    """

    def __init__(self, inbox, period: float = 0.01):
        super().__init__()
        self._inbox = inbox
        self._period = period
        self._pose = self.DeclareVectorInputPort("epm_pose", 6)
        # [last command (6), whether it is held (1)]
        initial = np.concatenate([np.full(6, np.nan), [0.0]])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort("epm_command", 6, self._calc, {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    @property
    def inbox(self):
        return self._inbox

    def _update(self, context, discrete_state):
        values = context.get_discrete_state(self._state).value().copy()
        kind, message = self._inbox.latest()
        last = values[:6]
        if kind == "goal":
            values[:6], values[6] = message, 0.0
        elif kind == "velocity":
            if not np.all(np.isfinite(last)):
                last = np.asarray(self._pose.Eval(context), dtype=float)
            p = last[:3] + message[:3] * self._period
            m = last[3:] + np.cross(message[3:], last[3:]) * self._period
            values[:6], values[6] = np.concatenate([p, m / np.linalg.norm(m)]), 0.0
        else:
            values[6] = 1.0     # hold: the guard keeps the EPM where it is
        discrete_state.set_value(self._state, values)

    def _calc(self, context, out: BasicVector) -> None:
        values = context.get_discrete_state(self._state).value()
        out.SetFromVector(np.full(6, np.nan) if values[6] > 0.5 else values[:6])


def channel_sinks(outputs):
    """The outputs of `outputs` (OutputsConfig) that take the run's channels, made (the
    Foxglove server not yet listening: it starts once told the run's topics; the MCAP file
    not yet created: at its first message)."""
    sinks = []
    if outputs.mcap is not None:
        sinks.append(Ros2McapFile(outputs.mcap.path, outputs.mcap.compression))
    if outputs.foxglove is not None:
        config = outputs.foxglove
        sinks.append(FoxgloveLive(config.host, config.port, config.wait_for_client,
                                   config.backlog))
    if outputs.ros2 is not None:
        sinks.append(Ros2Topics(outputs.ros2.domain_id, outputs.ros2.loopback))
    return sinks


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def add_channel_outputs(builder, station, scenario, wall_map=None, announce=_to_stderr):
    """Connects the scenario's channel outputs (and the EPM's goal topic) beside `station`
    in `builder` and returns their ChannelLogger, or None when the scenario has none.
    `wall_map`: the run's map of the wall's pressure (app/run.py `add_wall_pressure`), if
    any, for its image channel. `announce` gets one line per live server."""
    outputs = scenario.outputs
    if outputs.mcap is None and outputs.foxglove is None and outputs.ros2 is None:
        return None
    sinks = channel_sinks(outputs)
    logger = add_channel_logger(builder, station, scenario, sinks, wall_map=wall_map)
    for sink in sinks:
        if hasattr(sink, "start"):   # told the run's topics by the logger: now listening
            sink.start()
        if not sink.fatal and announce is not None:
            announce(f"live: {sink.name}")
    if outputs.ros2 is not None and outputs.ros2.epm_command:
        topics = next(s for s in sinks if hasattr(s, "dds_participant"))
        inbox = GoalInbox(hold_after=outputs.ros2.hold_after,
                          dds_participant=topics.dds_participant)
        source = builder.AddNamedSystem("ros2.epm_command", EpmGoalSource(inbox))
        builder.Connect(station.GetOutputPort("epm.pose"), source.GetInputPort("epm_pose"))
        builder.Connect(source.GetOutputPort("epm_command"),
                        station.GetInputPort("epm.command"))
    return logger
