"""A simulated operator: a hand on the stylus that pursues the lumen and yields to the
feedback force, so teleoperation runs in scripts, tests and benchmarks.

The hand holds the stylus through an impedance (stiffness, damping) toward a hand target
that the operator's intent moves:
- advancing: while the lumen is in view and near the image centre, push the target away
  (-z_D) at `advance_speed`; when the stylus reaches the front of the workspace (pushed by
  the hand or by the guidance), press the clutch, bring it back to the rear, release
  (indexing), and go on;
- steering: turn toward where the lumen appears, after a reaction delay: the target's
  sideways and vertical position goes to `steer_gain` times the lumen's offset (the ray's
  x and -y in the camera frame, i.e. the sine of its angle) with the time constant
  `steer_time`; while clutched the hand re-centres;
- off-centre beyond the cone for `push_after` s (a bend the capsule cannot turn in
  place): push on at a fraction of the speed while steering;
- lumen lost: stop advancing, centre the stylus sideways and draw it back slowly (back
  off); with the lead mapping (`cruise_offset`), hold a lead behind the capsule and, with
  `search_offset`, keep turning toward the side where the lumen was last seen.
The feedback force acts on the stylus through the device's motors; the hand resists it
only through its impedance, so a guiding force moves the stylus: the operator yields.
"""

import dataclasses

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.schema import need_range


@dataclasses.dataclass
class OperatorConfig:
    """The simulated operator. YAML-loadable; all fields default."""

    # Hand impedance on the stylus: stiffness (N/m) and damping (N s/m); human grip
    # stiffness is 100-400 N/m in light holding.
    hand_stiffness: float = 150.0
    hand_damping: float = 3.0
    # Stylus speed away from the operator while advancing (m/s), and back while clutched.
    advance_speed: float = 0.005
    return_speed: float = 0.04
    # Advance only while the lumen is within this angle of the image centre (deg).
    advance_cone_deg: float = 40.0
    # Steering: stylus displacement (m) per unit lumen offset (sin of its angle), reached
    # with time constant steer_time (s), after the visual loop's reaction delay (s).
    steer_gain: float = 0.05
    steer_time: float = 0.3
    reaction_time: float = 0.25
    # Off-centre beyond the cone for longer than push_after (s), push on at push_fraction of
    # the advance speed (0: wait for the lumen to come to the centre).
    push_after: float = 3.0
    push_fraction: float = 0.5
    # Back-off speed while the lumen is out of view (m/s).
    back_off_speed: float = 0.002
    # Fraction of the workspace depth used before indexing.
    stroke_fraction: float = 0.8
    # For the lead mapping: instead of stroking, hold the stylus this far forward of the
    # centre while the lumen is near the image centre (m), back at the centre when it is
    # off-centre, and behind it when it is lost. 0: stroke and index.
    cruise_offset: float = 0.0
    # For the lead mapping: while the lumen is out of view, besides backing off, hold the
    # stylus this far toward the side where the lumen was last seen (m): keep turning the
    # way it went (right when it was seen near the centre). 0: centre the stylus.
    search_offset: float = 0.0
    # Not found after search_sweep_after (s): the side turned toward sweeps around the image
    # once every search_sweep_period (s).
    search_sweep_after: float = 2.0
    search_sweep_period: float = 8.0
    # For the lead mapping: regulate the capsule's speed as seen in the video (its forward
    # speed, m/s) instead of holding the stylus at cruise_offset: push the stylus forward
    # while the capsule goes slower than this, draw it back while faster, at speed_gain
    # metres of stylus per second per (m/s) of error (at most return_speed). The forward
    # offset stays within the stroke; the speed is seen through speed_time (s) of
    # low-pass. 0: hold cruise_offset.
    target_speed: float = 0.0
    speed_gain: float = 1.0
    speed_time: float = 0.5
    # Regulating, with the stylus at the front of its stroke and the capsule not moving
    # (below a fifth of target_speed) for stall_after (s): treat the view as misleading:
    # back off and search for retreat_time (s) as if the lumen were lost, then go on.
    stall_after: float = 5.0
    retreat_time: float = 3.0
    # Sense of direction (with the `way_forward` input): when the camera looks back the way
    # the capsule came (the way forward more than this angle behind the image plane, deg),
    # the lumen in view is the way out: search, turning toward the way forward. 0: off.
    turn_back_deg: float = 0.0
    # Update period of the intent (s); the hand force itself follows the stylus at the
    # device's servo rate.
    period: float = 0.01


def check_operator_config(config: OperatorConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.push_after, "simulated.push_after", ">= 0", "s")
    need_range(config.push_fraction, "simulated.push_fraction", "[0, 1]")
    need_range(config.cruise_offset, "simulated.cruise_offset", ">= 0", "m")
    need_range(config.search_offset, "simulated.search_offset", ">= 0", "m")
    for name in ("steer_time", "speed_time", "search_sweep_period"):
        need_range(getattr(config, name), f"simulated.{name}", "> 0", "s")
    for name, unit in (("hand_stiffness", "N/m"), ("hand_damping", "N s/m"),
                       ("advance_speed", "m/s"), ("return_speed", "m/s"),
                       ("target_speed", "m/s"), ("speed_gain", ""),
                       ("search_sweep_after", "s"), ("stall_after", "s"),
                       ("retreat_time", "s"), ("turn_back_deg", "deg"), ("steer_gain", "m"),
                       ("reaction_time", "s"), ("back_off_speed", "m/s")):
        need_range(getattr(config, name), f"simulated.{name}", ">= 0", unit)
    need_range(config.stroke_fraction, "simulated.stroke_fraction", "(0, 1]")
    need_range(config.advance_cone_deg, "simulated.advance_cone_deg", "(0, 90]", "deg")
    need_range(config.period, "simulated.period", "> 0", "s")


class SimulatedOperator(LeafSystem):
    """The hand (module docstring).

    .. pydrake_system::

        name: SimulatedOperator
        input_ports:
        - stylus
        - stylus_velocity
        - lumen_visible
        - lumen_ray
        - forward_speed (optional)
        - way_forward (optional)
        output_ports:
        - hand_force
        - buttons
        - intent

    stylus, stylus_velocity: the device's. lumen_visible, lumen_ray: what the operator sees
    (the lumen tracker's outputs, or the truth). forward_speed: the capsule's speed along
    its camera axis as the video shows it (m/s; needed with `target_speed`). way_forward: the
    way the capsule has been going, in the camera frame (unit, or zeros; `WayForward`; used
    with `turn_back_deg`). hand_force: on the stylus (N, D), from the
    hand impedance toward the hand target. buttons: [clutch, mode]. intent: [hand target
    (3), phase (0 advancing, 1 returning, 2 backing off)].

    Args:
        config: OperatorConfig.
        workspace_half_extents: the device's (m).
    """

    def __init__(self, config: OperatorConfig, workspace_half_extents):
        super().__init__()
        check_operator_config(config)
        self._config = config
        self._half = np.asarray(workspace_half_extents, dtype=float)
        self._delay_steps = max(1, int(round(config.reaction_time / config.period)))
        self._stylus = self.DeclareVectorInputPort("stylus", 9)
        self._velocity = self.DeclareVectorInputPort("stylus_velocity", 3)
        self._visible = self.DeclareVectorInputPort("lumen_visible", 1)
        self._ray = self.DeclareVectorInputPort("lumen_ray", 3)
        self._speed = self.DeclareVectorInputPort("forward_speed", 1)
        self._way = self.DeclareVectorInputPort("way_forward", 3)
        self._regulating = config.cruise_offset > 0.0 and config.target_speed > 0.0
        # [target (3), phase, clutch, seen offsets ring (2 x delay), seen visible ring (delay)]
        n = self._delay_steps
        start_z = 0.0 if config.cruise_offset > 0.0 else self._half[2] * config.stroke_fraction
        # [..., stalled for (s), retreat left (s), speed seen (m/s), time off-centre (s)]
        initial = np.concatenate([[0.0, 0.0, start_z, 0.0, 0.0], np.zeros(3 * n),
                                  [0.0, 0.0, 0.0, 0.0]])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort("hand_force", 3, self._calc_force)
        self.DeclareVectorOutputPort(
            "buttons", 2,
            lambda c, out: out.SetFromVector(
                [c.get_discrete_state(self._state).value()[4], 0.0]), {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "intent", 4,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[:4]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

    def _calc_force(self, context, output):
        c = self._config
        target = context.get_discrete_state(self._state).value()[:3]
        p = np.asarray(self._stylus.Eval(context)[:3], dtype=float)
        v = np.asarray(self._velocity.Eval(context), dtype=float)
        output.SetFromVector(c.hand_stiffness * (target - p) - c.hand_damping * v)

    def _update(self, context, discrete_state):
        c = self._config
        x = context.get_discrete_state(self._state).value().copy()
        n = self._delay_steps
        visible_now = float(self._visible.Eval(context)[0]) > 0.5
        ray = np.asarray(self._ray.Eval(context), dtype=float)
        if not np.all(np.isfinite(ray)):
            visible_now = False
        # What the operator reacts to now is what was on the screen `reaction_time` ago.
        offsets = x[5:5 + 2 * n].reshape(n, 2)
        visibles = x[5 + 2 * n:5 + 3 * n]
        seen_offset, seen_visible = offsets[0].copy(), visibles[0] > 0.5
        offsets = np.roll(offsets, -1, axis=0)
        visibles = np.roll(visibles, -1)
        offsets[-1] = [ray[0], -ray[1]] if visible_now else offsets[-2]
        visibles[-1] = float(visible_now)
        x[5:5 + 2 * n], x[5 + 2 * n:5 + 3 * n] = offsets.ravel(), visibles

        target, phase = x[:3], x[3]
        front = -self._half[2] * c.stroke_fraction
        rear = self._half[2] * c.stroke_fraction
        dt = c.period
        if c.cruise_offset > 0.0 and c.turn_back_deg > 0.0 and self._way.HasValue(context):
            way = np.asarray(self._way.Eval(context), dtype=float)
            if np.all(np.isfinite(way)) and np.linalg.norm(way) > 0.5 \
                    and way[2] < -np.sin(np.radians(c.turn_back_deg)):
                # Looking back the way it came: what is in view is the way out. Search,
                # turning toward the way forward (its side in the image; right if straight
                # behind).
                seen_visible = False
                side = np.array([way[0], -way[1]])
                seen_offset = side if np.linalg.norm(side) > 0.05 else np.array([1.0, 0.0])
        if c.cruise_offset > 0.0:
            offset_angle = np.degrees(np.arcsin(np.clip(np.linalg.norm(seen_offset), 0, 1)))
            x[-1] = 0.0 if (seen_visible and offset_angle < c.advance_cone_deg) else x[-1] + dt
            if self._regulating:
                # The capsule's speed as the operator sees it in the video (low-passed).
                v_now = float(self._speed.Eval(context)[0])
                if np.isfinite(v_now):
                    x[-2] += (v_now - x[-2]) * min(1.0, dt / c.speed_time)
                # Pushing at the front of the stroke and going nowhere: retreat and search.
                at_front = target[2] <= -self._half[2] * c.stroke_fraction + 1e-6
                stalled = at_front and abs(x[-2]) < 0.2 * c.target_speed and x[-3] <= 0.0
                x[-4] = x[-4] + dt if stalled else 0.0
                if x[-4] > c.stall_after:
                    x[-4], x[-3] = 0.0, c.retreat_time
                if x[-3] > 0.0:
                    x[-3] = max(0.0, x[-3] - dt)
                    seen_visible = False
                    x[-1] += dt
            if not seen_visible:
                phase, goal = 2.0, 0.5 * c.cruise_offset
            elif offset_angle < c.advance_cone_deg or x[-1] > c.push_after:
                phase = 0.0
                wanted = c.target_speed * (1.0 if x[-1] == 0.0 else c.push_fraction)
                if self._regulating:
                    rate = np.clip(c.speed_gain * (wanted - x[-2]), -c.return_speed,
                                   c.return_speed)
                    goal = float(np.clip(target[2] - rate * dt,
                                         -self._half[2] * c.stroke_fraction,
                                         0.5 * c.cruise_offset))
                else:
                    goal = -c.cruise_offset * (1.0 if x[-1] == 0.0 else c.push_fraction)
            else:
                phase, goal = 0.0, min(target[2], 0.0) if self._regulating else 0.0
            if self._regulating and phase == 0.0:
                target[2] = goal
            else:
                speed = c.advance_speed if goal < target[2] else c.back_off_speed * 4.0
                target[2] += np.clip(goal - target[2], -speed * dt, speed * dt)
            if seen_visible:
                aim = c.steer_gain * seen_offset
            else:  # search: turn toward where the lumen was last seen, then sweep around
                norm = np.linalg.norm(seen_offset)
                side = seen_offset / norm if norm > 0.05 else np.array([1.0, 0.0])
                sweep = 2.0 * np.pi * max(0.0, x[-1] - c.search_sweep_after) \
                    / c.search_sweep_period
                aim = c.search_offset * np.array([
                    side[0] * np.cos(sweep) - side[1] * np.sin(sweep),
                    side[0] * np.sin(sweep) + side[1] * np.cos(sweep)])
            target[:2] += (aim - target[:2]) * min(1.0, dt / c.steer_time)
            target[:2] = np.clip(target[:2], -self._half[:2], self._half[:2])
            x[:3], x[3] = target, phase
            discrete_state.set_value(self._state, x)
            return
        if phase == 1.0:  # returning with the clutch held
            target[2] = min(rear, target[2] + c.return_speed * dt)
            target[:2] *= max(0.0, 1.0 - dt / 0.3)  # re-centre sideways
            if target[2] >= rear:
                phase, x[4] = 0.0, 0.0
        else:
            offset_angle = np.degrees(np.arcsin(np.clip(np.linalg.norm(seen_offset), 0, 1)))
            if seen_visible:
                phase = 0.0
                x[-1] = 0.0 if offset_angle < c.advance_cone_deg else x[-1] + dt
                if offset_angle < c.advance_cone_deg:
                    target[2] -= c.advance_speed * dt
                elif x[-1] > c.push_after:
                    # Off-centre for a while (a bend the capsule cannot turn in place):
                    # push on slowly while steering, as an endoscopist slides by.
                    target[2] -= c.push_fraction * c.advance_speed * dt
            else:
                phase = 2.0
                target[2] = min(rear, target[2] + c.back_off_speed * dt)
            aim = c.steer_gain * seen_offset if seen_visible else np.zeros(2)
            target[:2] += (aim - target[:2]) * min(1.0, dt / c.steer_time)
            target[:2] = np.clip(target[:2], -self._half[:2], self._half[:2])
            stylus_z = float(self._stylus.Eval(context)[2])
            if target[2] <= front or stylus_z <= front:  # at the front: index
                phase, x[4] = 1.0, 1.0
                target[2] = max(target[2], stylus_z)
        x[:3], x[3] = target, phase
        discrete_state.set_value(self._state, x)


class ForwardSpeed(LeafSystem):
    """The capsule's speed along its camera's axis (m/s): what the video's motion shows
    the operator (forward positive).

    .. pydrake_system::

        name: ForwardSpeed
        input_ports:
        - capsule_state
        output_ports:
        - forward_speed

    capsule_state: [q wxyz, p_WB, w_WB, v_WB] of the capsule's floating body.

    Args:
        z_BC: the camera's optical axis in the capsule's body frame.
    """

    def __init__(self, z_BC):
        super().__init__()
        self._z_BC = np.asarray(z_BC, dtype=float) / np.linalg.norm(z_BC)
        self._state = self.DeclareVectorInputPort("capsule_state", 13)
        self.DeclareVectorOutputPort("forward_speed", 1, self._calc)

    def _calc(self, context, output):
        x = np.asarray(self._state.Eval(context), dtype=float)
        output.SetAtIndex(0, float(x[10:13] @ (rotation_from_quaternion(x[:4]) @ self._z_BC)))


class WayForward(LeafSystem):
    """The way the capsule has been going, as the operator knows it from the external view
    (or a localisation display): from a trail point that follows the capsule with a lag
    (low-pass of its position, time constant `trail_time`) to the capsule, in the camera
    frame, unit; zeros until the capsule is `min_distance` from the trail.

    .. pydrake_system::

        name: WayForward
        input_ports:
        - capsule_state
        output_ports:
        - way_C

    Args:
        R_BC: the camera's orientation in the capsule body (3, 3).
        start: the capsule's start position (where the trail begins).
    """

    def __init__(self, R_BC, start, trail_time: float = 10.0, min_distance: float = 0.02,
                 period: float = 0.05):
        super().__init__()
        self._R_BC = np.asarray(R_BC, dtype=float)
        self._alpha = min(1.0, period / trail_time)
        self._min = min_distance
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._trail = self.DeclareDiscreteState(np.asarray(start, dtype=float))
        self.DeclareVectorOutputPort("way_C", 3, self._calc, {self.all_sources_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _update(self, context, discrete_state):
        x = np.asarray(self._state_port.Eval(context), dtype=float)
        trail = context.get_discrete_state(self._trail).value()
        if np.all(np.isfinite(x[4:7])):
            discrete_state.set_value(self._trail, trail + self._alpha * (x[4:7] - trail))

    def _calc(self, context, output):
        x = np.asarray(self._state_port.Eval(context), dtype=float)
        way = x[4:7] - context.get_discrete_state(self._trail).value()
        distance = np.linalg.norm(way)
        if not np.isfinite(distance) or distance < self._min:
            output.SetFromVector(np.zeros(3))
            return
        R_WC = rotation_from_quaternion(x[:4]) @ self._R_BC
        output.SetFromVector(R_WC.T @ (way / distance))
