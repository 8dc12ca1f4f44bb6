"""The scenario's channel outputs connected to a run: the MCAP file, the Foxglove server and
the ROS 2 topics all through one ChannelLogger (app/mcap_log.py), and the EPM's goal topic
into the station's `epm.command` input.

`channel_outputs_extend(scenario)` is `simulate`'s extend for them (None when the scenario
has none); its close hook closes every output.
"""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.app.mcap_log import Ros2McapFile, add_channel_logger


class EpmGoalSource(LeafSystem):
    """The latest EPM goal of a ROS 2 topic (app/live/ros2_out.py `GoalInbox`) as the
    station's `epm.command` ([p_WE, m_hat_W]; NaN before the first goal and after a lost
    link, which the EPM's guard turns into a hold).

    .. pydrake_system::

        name: EpmGoalSource
        output_ports:
        - epm_command
    """

    def __init__(self, inbox):
        super().__init__()
        self._inbox = inbox
        self.DeclareVectorOutputPort("epm_command", 6, self._calc,
                                     {self.time_ticket()})

    @property
    def inbox(self):
        return self._inbox

    def _calc(self, context, out: BasicVector) -> None:
        out.SetFromVector(np.asarray(self._inbox.command(), dtype=float))


def channel_sinks(outputs):
    """The outputs of `outputs` (OutputsConfig) that take the run's channels, made (servers
    started, the MCAP file not yet created: at its first message)."""
    sinks = []
    if outputs.mcap is not None:
        sinks.append(Ros2McapFile(outputs.mcap.path, outputs.mcap.compression))
    if outputs.foxglove is not None:
        from capsule_drake.app.live.foxglove_out import FoxgloveLive
        config = outputs.foxglove
        sinks.append(FoxgloveLive(config.host, config.port, config.wait_for_client))
    if outputs.ros2 is not None:
        from capsule_drake.app.live.ros2_out import Ros2Topics
        sinks.append(Ros2Topics(outputs.ros2.domain_id, outputs.ros2.loopback))
    return sinks


def channel_outputs_extend(scenario, announce=print):
    """`simulate`'s extend that connects the scenario's channel outputs (and the EPM's goal
    topic) to the run, or None when it has none. `announce` gets one line per live server."""
    outputs = scenario.outputs
    if outputs.mcap is None and outputs.foxglove is None and outputs.ros2 is None:
        return None

    def extend(builder, station):
        sinks = channel_sinks(outputs)
        for sink in sinks:
            if not sink.fatal and announce is not None:
                announce(f"live: {sink.name}")
        logger = add_channel_logger(builder, station, scenario, sinks)
        if outputs.ros2 is not None and outputs.ros2.epm_goal:
            from capsule_drake.app.live.ros2_out import GoalInbox
            topics = next(s for s in sinks if hasattr(s, "dds_participant"))
            inbox = GoalInbox(hold_after=outputs.ros2.hold_after,
                              dds_participant=topics.dds_participant)
            source = builder.AddNamedSystem("ros2.epm_goal", EpmGoalSource(inbox))
            builder.Connect(source.get_output_port(), station.GetInputPort("epm.command"))
        return logger.close

    return extend
