"""A one-degree-of-freedom bench for haptic teleoperation over a delayed link.

A hand holding the stylus (one mass, gripped by a spring-damper toward where the person
means to be, with the device's friction) talks through `TeleopChannel` (delay, jitter, loss,
and optionally the time-domain passivity scheme) to a virtual wall on the robot side, which
pushes back on the received stylus position. It isolates what the delay does to the force
feedback: stability (does the stylus settle on the wall, or bounce?) and transparency (how
close is the force the hand feels to the wall's?). Used by tests/test_channel.py and
notebooks/teleop_delay.ipynb.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.app.run import simulator_for
from capsule_drake.teleop.channel import ChannelConfig, PassivityConfig, TeleopChannel, \
    TeleopChannelConfig

PERIOD = 0.001  # the haptic loop's period (s)


class HandOnStylus(LeafSystem):
    """1-DoF haptic device held by a hand, along x of the device frame: the hand and the
    stylus as one mass (kg), gripped by a spring-damper (N/m, N s/m) toward the hand target
    `target(t)` (the person's intention), with the device's Coulomb friction (N, smoothed
    over 1 mm/s). State [x, v, work]: work (J) integrates the rendered force times the
    velocity, the energy the channel delivered to the hand, independently of the passivity
    observer."""

    def __init__(self, mass, grip_stiffness, grip_damping, friction, target):
        LeafSystem.__init__(self)
        self._params = (mass, grip_stiffness, grip_damping, friction)
        self._target = target
        self.DeclareContinuousState(3)
        self._force_port = self.DeclareVectorInputPort("force", 3)
        self.DeclareVectorOutputPort(
            "position", 3, lambda c, o: o.SetFromVector(
                [c.get_continuous_state_vector()[0], 0.0, 0.0]), {self.xc_ticket()})
        self.DeclareVectorOutputPort(
            "velocity", 3, lambda c, o: o.SetFromVector(
                [c.get_continuous_state_vector()[1], 0.0, 0.0]), {self.xc_ticket()})
        self.DeclareVectorOutputPort(
            "state", 3, lambda c, o: o.SetFromVector(
                c.get_continuous_state_vector().CopyToVector()), {self.xc_ticket()})

    def DoCalcTimeDerivatives(self, context, derivatives):
        mass, k, b, friction = self._params
        x, v, _ = context.get_continuous_state_vector().CopyToVector()
        force = self._force_port.Eval(context)[0]
        grip = k * (self._target(context.get_time()) - x) - b * v
        a = (force + grip - friction * math.tanh(v / 1e-3)) / mass
        derivatives.get_mutable_vector().SetFromVector([v, a, force * v])


class VirtualWall(LeafSystem):
    """Robot side: a virtual wall at x = 0 of the received stylus position, pushing back
    with stiffness (N/m), like the pseudo-force's wall term."""

    def __init__(self, stiffness):
        LeafSystem.__init__(self)
        self._position_port = self.DeclareVectorInputPort("position", 3)
        self.DeclareVectorOutputPort("force", 3, lambda c, o: o.SetFromVector(
            [-stiffness * max(self._position_port.Eval(c)[0], 0.0), 0.0, 0.0]))


class BenchRun(NamedTuple):
    """Signals of a run, sampled every PERIOD: time (s), stylus position (m) and velocity
    (m/s), the work done on the hand (J), the passivity observer's energy (J), the scheme's
    change to the force (N), and the force rendered to the hand (N)."""

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    work: np.ndarray
    energy: np.ndarray
    force_change: np.ndarray
    force: np.ndarray


def press_and_hold(t):
    """Hand target: from 2 mm outside the wall, in at 2 mm/s to 3 mm inside, then held."""
    return min(-0.002 + 0.002 * t, 0.003)


def run_delay_bench(delay, passivity, target=press_and_hold, x0=-0.002,
                    wall_stiffness=800.0, duration=10.0, jitter=0.0, loss=0.0,
                    mass=0.3, grip_stiffness=200.0, grip_damping=3.0,
                    friction=0.05) -> BenchRun:
    """Hand + device <-> TeleopChannel (`delay` s each way, with `jitter` and `loss`, the
    passivity scheme on or off) <-> virtual wall; the hand starts at x0 (m)."""
    builder = DiagramBuilder()
    hand = builder.AddSystem(HandOnStylus(mass, grip_stiffness, grip_damping, friction,
                                          target))
    link = ChannelConfig(delay=delay, jitter=jitter, loss=loss)
    config = TeleopChannelConfig(
        forward=link, backward=dataclasses.replace(link, seed=1),
        passivity=PassivityConfig(enabled=passivity))
    channel = builder.AddSystem(TeleopChannel(3, config))
    wall = builder.AddSystem(VirtualWall(wall_stiffness))
    builder.Connect(hand.GetOutputPort("position"), channel.GetInputPort("stylus_in"))
    builder.Connect(hand.GetOutputPort("position"), channel.GetInputPort("stylus_position"))
    builder.Connect(hand.GetOutputPort("velocity"), channel.GetInputPort("stylus_velocity"))
    builder.Connect(channel.GetOutputPort("stylus_out"), wall.get_input_port())
    builder.Connect(wall.get_output_port(), channel.GetInputPort("force_in"))
    builder.Connect(channel.GetOutputPort("force_out"), hand.get_input_port())
    logs = [LogVectorOutput(port, builder, PERIOD) for port in (
        hand.GetOutputPort("state"), channel.GetOutputPort("energy"),
        channel.GetOutputPort("force_change"), channel.GetOutputPort("force_out"))]
    diagram = builder.Build()
    simulator = simulator_for(diagram)
    context = simulator.get_mutable_context()
    hand.GetMyMutableContextFromRoot(context).SetContinuousState([x0, 0.0, 0.0])
    simulator.AdvanceTo(duration)
    state, energy, change, force = (log.FindLog(context).data() for log in logs)
    t = logs[0].FindLog(context).sample_times()
    return BenchRun(t, state[0], state[1], state[2], energy[0], change[0], force[0])
