"""Autonomous lumen following: the EPM moved so the capsule advances down the lumen.

`LumenFollower` is the robot's controller in place of the operator's hand. It sees what the
capsule's camera shows of the lumen (a ray in the camera frame and whether the lumen is in
view: from the lumen tracker, or from the lumen truth) and where the capsule is (its pose,
as an external localisation would give it); it knows the patient's skin (a body scan), so
that it keeps the magnet at its clearance. It knows nothing else of the colon.

The control law, every `period`:
- Heading h: the lumen direction in the world (the ray turned by the camera's orientation),
  low-passed, kept within `max_lead_deg` of the capsule's axis (a capsule the tissue holds
  back cannot wind up a large turn) and within `max_pitch_deg` of the horizontal.
- The EPM goes over the point `lead` ahead of the capsule's magnet along the horizontal
  projection of h (the lead is a fraction of the EPM's height above the magnet), as low
  as its clearance from the skin allows (+ `height_margin`), its moment turned so that
  its field at the capsule's magnet points along h (`field_aligning_moment_direction`),
  as the teleoperation mapping's lead mode does. The
  attraction then pulls the capsule forward and the field turns it toward the lumen.
- Speed: the lead grows while the capsule moves slower than `target_speed` along h and
  shrinks while it moves faster (quickly above `overspeed` times the target); the command
  moves at most `max_epm_speed`, so a capsule that breaks free does not drag the EPM on.
- Stall: with the lead at its longest and no progress for `stall_after`, push: the lead
  sweeps between `push_lead` and `push_lead_low` and the heading wiggles sideways; if
  the capsule still does not move within `push_time`, back off (the EPM `backoff_lead`
  behind the capsule for `backoff_time`) and retry.
- Lumen lost (not seen for `lost_after`): back off, then search: the heading sweeps a cone
  around the last forward direction the lumen was seen in; when it is seen again, go on.
- Sense of direction: the controller drops breadcrumbs along the capsule's path (its own
  memory of the poses it was given). A lumen direction that heads into crumbs older than
  the one the capsule is at is the way out (the capsule has turned back, or the truth's
  "ahead" flipped with the camera): ignored, and the search turns toward the way forward
  (along the crumbs from older to newer around the capsule). This holds in the sigmoid's
  hairpins, where the way forward does point back across the abdomen.

A non-finite capsule pose holds the command; a non-finite lumen ray counts as not seen.
"""

import dataclasses

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.primitives import Demultiplexer

from capsule_drake.epm_path import field_aligning_moment_direction
from capsule_drake.teleop.mapping import horizontal, lead_at_most, limit_pitch, turn

LUMEN_SOURCES = ("truth", "truth_point", "detected")

# Modes of the controller (the `status` output's first element).
CRUISE, PUSH, BACKOFF, SEARCH = 0.0, 1.0, 2.0, 3.0


@dataclasses.dataclass
class LumenFollowerConfig:
    """How the autonomous controller drives the EPM. YAML-loadable; all fields default."""

    # Update period of the controller (s).
    period: float = 0.05
    # Speed the capsule is driven at along its heading (m/s).
    target_speed: float = 0.01
    # Leads are fractions of the EPM's height above the capsule's magnet (the horizontal pull
    # peaks near 0.6 of the height, where it also about equals the vertical attraction).
    # Rate at which the lead grows per unit of speed shortfall (1 per m).
    lead_gain: float = 10.0
    # Shortest and longest lead of the EPM ahead of the capsule's magnet in cruise.
    min_lead: float = 0.2
    max_lead: float = 0.7
    # Above overspeed * target_speed the lead shrinks at brake_rate (1/s).
    overspeed: float = 2.0
    brake_rate: float = 0.5
    # Time constant of the capsule's speed estimate (s).
    speed_time: float = 1.0
    # Time constant with which the heading follows the lumen direction (s).
    heading_time: float = 0.5
    # The heading stays within this angle of the capsule's axis (deg) and of the
    # horizontal (deg).
    max_lead_deg: float = 40.0
    max_pitch_deg: float = 45.0
    # Height of the EPM's centre above the lowest its clearance from the skin allows (m).
    height_margin: float = 0.0
    # Fastest the EPM's commanded position moves over the patient (m/s).
    max_epm_speed: float = 0.03
    # Stall: lead at >= 90 % of max_lead and speed below stall_speed_fraction *
    # target_speed for stall_after (s) -> push.
    stall_speed_fraction: float = 0.2
    stall_after: float = 6.0
    # Push: the lead sweeps from push_lead down to push_lead_low and back once per
    # push_sweep_period (s) (a climbing lumen wants the vertical attraction of a short lead
    # to lift the capsule off the floor, a level one the pull of a long lead), for
    # push_time (s), while the heading wiggles sideways (deg, period s); progress along the
    # heading of unstick_distance (m) counts as unstuck.
    push_lead: float = 1.0
    push_lead_low: float = 0.0
    push_sweep_period: float = 12.0
    push_time: float = 12.0
    wiggle_deg: float = 25.0
    wiggle_period: float = 4.0
    unstick_distance: float = 0.01
    # Back off: the EPM this far behind the capsule's magnet, for this long (s).
    backoff_lead: float = 0.3
    backoff_time: float = 3.0
    # Lumen not seen for lost_after (s) -> back off, then search: the heading sweeps a cone
    # of half-angle search_cone_deg (deg) once per search_period (s) with the EPM
    # search_lead ahead; after search_time (s) without the lumen, back off again.
    lost_after: float = 1.0
    search_cone_deg: float = 35.0
    search_period: float = 8.0
    search_lead: float = 0.1
    search_time: float = 16.0
    # Sense of direction: the controller drops a breadcrumb wherever the capsule has moved
    # crumb_spacing (m) from the last one (at most max_crumbs; the oldest go first). A
    # direction d is backward when the point look_ahead (m) along d from the capsule lies
    # within crumb_radius (m) of a crumb older than the one nearest the capsule (it heads
    # into where the capsule came from).
    crumb_spacing: float = 0.01
    max_crumbs: int = 400
    look_ahead: float = 0.03
    crumb_radius: float = 0.015


def check_lumen_follower_config(config: LumenFollowerConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    for name in ("period", "speed_time", "heading_time", "wiggle_period", "search_period",
                 "max_epm_speed", "target_speed", "crumb_spacing", "look_ahead",
                 "crumb_radius"):
        if not getattr(config, name) > 0.0:
            raise ValueError(f"lumen follower {name} must be > 0, got {getattr(config, name)}")
    for name in ("lead_gain", "min_lead", "brake_rate", "height_margin",
                 "stall_speed_fraction", "stall_after", "push_time", "wiggle_deg",
                 "unstick_distance", "backoff_lead", "backoff_time", "lost_after",
                 "search_cone_deg", "search_lead", "search_time"):
        if not getattr(config, name) >= 0.0:
            raise ValueError(f"lumen follower {name} must be >= 0, got {getattr(config, name)}")
    if not config.max_lead >= config.min_lead:
        raise ValueError("lumen follower max_lead must be >= min_lead")
    if not config.push_lead >= config.push_lead_low >= 0.0:
        raise ValueError("lumen follower needs push_lead >= push_lead_low >= 0")
    if not config.push_sweep_period > 0.0:
        raise ValueError("lumen follower push_sweep_period must be > 0")
    if not config.max_crumbs >= 3:
        raise ValueError("lumen follower max_crumbs must be >= 3")
    if not config.overspeed > 1.0:
        raise ValueError("lumen follower overspeed must be > 1")
    for name in ("max_lead_deg", "max_pitch_deg", "search_cone_deg"):
        if not getattr(config, name) <= 90.0:
            raise ValueError(f"lumen follower {name} must be <= 90 deg")


# Layout of the discrete state.
_CMD = slice(0, 6)      # the EPM command [p_WE, m_hat_W]
_H = slice(6, 9)        # heading (world, unit)
_LEAD = 9               # lead (fraction of the EPM's height above the magnet)
_NCRUMB = 10            # number of breadcrumbs
# 11, 12: unused
_V = 13                 # filtered speed along the heading (m/s)
_PREV = slice(14, 17)   # capsule position at the previous update
_MODE = 17
_MODE_T = 18            # time in the mode (s)
_STALL_T = 19           # time stalled (s)
_SEEN = slice(20, 23)   # last lumen direction seen (world, unit; zeros: none yet)
_LOST_T = 23            # time since the lumen was last seen (s)
_ANCHOR = slice(24, 27)  # capsule position when the push began
_INIT = 27              # 0 until the first update
_SIDE = 28              # +-1: side the next wiggle starts to
_BASE = slice(29, 32)   # the push's / search's base heading
_WAY = slice(32, 35)    # the way forward (world, unit)
_CRUMBS = 35            # breadcrumbs (max_crumbs x 3) from here on


class LumenFollower(LeafSystem):
    """Lumen ray + capsule pose -> EPM command [p_WE, m_hat_W] (module docstring).

    .. pydrake_system::

        name: LumenFollower
        input_ports:
        - capsule_pose
        - lumen_ray
        - lumen_visible
        output_ports:
        - epm_command
        - heading
        - status

    capsule_pose: [q_WB wxyz (4), p_WB (3)] of the capsule body. lumen_ray: unit ray toward
    the lumen in the camera frame (x right, y down, z forward). lumen_visible: 1 when the
    lumen is in view. epm_command: [p_WE (3), m_hat_W (3)], the EPM's centre and moment
    direction (for the station's `epm.command`). heading: the commanded heading h_W (unit).
    status: [mode (0 cruise, 1 push, 2 back off, 3 search), lead (fraction of the EPM's
    height above the capsule's magnet), speed along the heading
    (m/s), time since the lumen was seen (s)].

    Args:
        config: LumenFollowerConfig.
        X_BC: the camera's pose in the capsule body (RigidTransform).
        p_BM: the capsule magnet's position in the body (where the field is aimed).
        floor: function (x, y, m_hat) -> lowest allowed EPM centre height (e.g.
            `EpmGuard.lowest_centre_height`).
    """

    def __init__(self, config: LumenFollowerConfig, X_BC, p_BM, floor):
        super().__init__()
        check_lumen_follower_config(config)
        self._config = config
        self._R_BC = np.asarray(X_BC.rotation().matrix())
        self._p_BM = np.asarray(p_BM, dtype=float)
        self._floor = floor
        self._pose = self.DeclareVectorInputPort("capsule_pose", 7)
        self._ray = self.DeclareVectorInputPort("lumen_ray", 3)
        self._visible = self.DeclareVectorInputPort("lumen_visible", 1)
        self._state = self.DeclareDiscreteState(
            BasicVector(np.zeros(_CRUMBS + 3 * config.max_crumbs)))
        self.DeclareVectorOutputPort(
            "epm_command", 6,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[_CMD]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "heading", 3,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[_H]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort("status", 4, self._calc_status, {self.xd_ticket()})
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

    def command_for(self, p_WE_xy, heading, p_WM):
        """[p_WE, m_hat_W]: the EPM over (x, y) at `height_margin` above its floor, its
        moment aligning the field at the capsule's magnet p_WM with `heading`."""
        p = np.array([p_WE_xy[0], p_WE_xy[1], 0.0])
        m = np.array([0.0, 0.0, 1.0])
        for _ in range(3):  # the floor depends a little on the moment's tilt
            p[2] = self._floor(p[0], p[1], m) + self._config.height_margin
            u = p_WM - p
            m = field_aligning_moment_direction(u / np.linalg.norm(u), heading)
        return np.concatenate([p, m])

    def _calc_status(self, context, output):
        x = context.get_discrete_state(self._state).value()
        output.SetFromVector([x[_MODE], x[_LEAD], x[_V], x[_LOST_T]])

    def _pose_of(self, context):
        pose = np.asarray(self._pose.Eval(context), dtype=float)
        if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:4]) < 1e-6:
            return None
        R_WB = Quaternion(pose[:4] / np.linalg.norm(pose[:4])).rotation()
        return R_WB, pose[4:7]

    def _initialize(self, context, discrete_state):
        pose = self._pose_of(context)
        x = context.get_discrete_state(self._state).value().copy()
        if pose is None:
            return
        self._start(x, *pose)
        discrete_state.set_value(self._state, x)

    def _start(self, x, R_WB, p):
        """First sight of the capsule: the EPM over its magnet, heading along its axis, the
        way forward along its axis (it is put in looking down the lumen)."""
        z_W = (R_WB @ self._R_BC)[:, 2]
        p_WM = p + R_WB @ self._p_BM
        x[:] = 0.0
        x[_H] = z_W
        spacing = self._config.crumb_spacing
        crumbs = x[_CRUMBS:].reshape(-1, 3)
        crumbs[:3] = [p - 2.0 * spacing * z_W, p - spacing * z_W, p]
        x[_NCRUMB] = 3.0
        x[_PREV] = p
        x[_WAY] = z_W
        x[_SIDE] = 1.0
        x[_INIT] = 1.0
        x[_LEAD] = self._config.min_lead
        x[_CMD] = self.command_for(p_WM[:2], z_W, p_WM)

    def _update(self, context, discrete_state):
        c = self._config
        dt = c.period
        x = context.get_discrete_state(self._state).value().copy()
        pose = self._pose_of(context)
        if pose is None:  # hold the command
            return
        R_WB, p = pose
        if x[_INIT] < 0.5:
            self._start(x, R_WB, p)
        R_WC = R_WB @ self._R_BC
        z_W = R_WC[:, 2]
        p_WM = p + R_WB @ self._p_BM

        # Sense of direction: breadcrumbs, the crumb nearest the capsule, the way forward.
        crumbs = x[_CRUMBS:].reshape(-1, 3)
        n = int(x[_NCRUMB])
        if np.linalg.norm(p - crumbs[n - 1]) > c.crumb_spacing:
            if n == len(crumbs):
                crumbs[:-1] = crumbs[1:].copy()
                n -= 1
            crumbs[n] = p
            n += 1
            x[_NCRUMB] = n
        trail = crumbs[:n]
        k = int(np.argmin(np.linalg.norm(trail - p, axis=1)))
        ahead = trail[min(k + 2, n - 1)] if k + 2 <= n - 1 else p
        w = ahead - trail[max(k - 2, 0)]
        if np.linalg.norm(w) > 0.5 * c.crumb_spacing:
            x[_WAY] = w / np.linalg.norm(w)
        way = x[_WAY].copy()
        older = trail[:max(k - 1, 0)]

        def backward(direction):
            """Whether `direction` heads into where the capsule came from."""
            if len(older) == 0:
                return False
            q = p + c.look_ahead * direction
            return bool(np.min(np.linalg.norm(older - q, axis=1)) < c.crumb_radius)

        # Speed along the heading.
        v_now = float((p - x[_PREV]) @ x[_H]) / dt
        x[_PREV] = p
        x[_V] += (v_now - x[_V]) * min(1.0, dt / c.speed_time)

        # What the camera shows of the lumen.
        ray = np.asarray(self._ray.Eval(context), dtype=float)
        visible = (float(self._visible.Eval(context)[0]) > 0.5 and np.all(np.isfinite(ray))
                   and np.linalg.norm(ray) > 0.5)
        d = R_WC @ (ray / np.linalg.norm(ray)) if visible else None
        if visible and backward(d):
            visible = False  # looking back the way it came: that lumen is the way out
        if visible:
            x[_SEEN] = d
            x[_LOST_T] = 0.0
        else:
            x[_LOST_T] += dt
        seen = x[_SEEN] if np.linalg.norm(x[_SEEN]) > 0.5 else z_W

        def forward_base():
            """The last lumen seen if it lies forward, else the way forward."""
            return way if backward(seen) else seen

        mode = x[_MODE]
        x[_MODE_T] += dt
        lost = x[_LOST_T] > c.lost_after

        def switch(new_mode):
            x[_MODE], x[_MODE_T] = new_mode, 0.0

        if mode == CRUISE:
            if lost:
                switch(BACKOFF)
                x[_BASE] = forward_base()
            else:
                x[_LEAD] += c.lead_gain * (c.target_speed - x[_V]) * dt
                if x[_V] > c.overspeed * c.target_speed:
                    x[_LEAD] -= c.brake_rate * dt
                x[_LEAD] = np.clip(x[_LEAD], c.min_lead, c.max_lead)
                stalled = (x[_LEAD] >= 0.9 * c.max_lead
                           and x[_V] < c.stall_speed_fraction * c.target_speed)
                x[_STALL_T] = x[_STALL_T] + dt if stalled else 0.0
                if x[_STALL_T] > c.stall_after:
                    switch(PUSH)
                    x[_ANCHOR] = p
                    x[_BASE] = seen
                    x[_STALL_T] = 0.0
        elif mode == PUSH:
            if (p - x[_ANCHOR]) @ x[_BASE] > c.unstick_distance:
                switch(CRUISE)  # go on with the lead that got it moving
                x[_LEAD] = np.clip(x[_LEAD], c.min_lead, c.max_lead)
            elif x[_MODE_T] > c.push_time or lost:
                switch(BACKOFF)
                x[_BASE] = forward_base()
                x[_SIDE] = -x[_SIDE]
        elif mode == BACKOFF:
            if x[_MODE_T] > c.backoff_time:
                if x[_LOST_T] > 0.0:
                    switch(SEARCH)
                else:
                    switch(CRUISE)
                    x[_LEAD] = c.min_lead
                    x[_STALL_T] = 0.0
        elif mode == SEARCH:
            if x[_LOST_T] == 0.0:
                switch(CRUISE)
                x[_LEAD] = c.min_lead
                x[_STALL_T] = 0.0
            elif x[_MODE_T] > c.search_time:
                switch(BACKOFF)
                x[_BASE] = way

        # The heading wanted and the lead of the mode.
        mode = x[_MODE]
        if mode == CRUISE:
            target, lead = seen, x[_LEAD]
        elif mode == PUSH:
            swing = x[_SIDE] * np.radians(c.wiggle_deg) * np.sin(
                2.0 * np.pi * x[_MODE_T] / c.wiggle_period)
            x[_LEAD] = c.push_lead_low + (c.push_lead - c.push_lead_low) * 0.5 * (
                1.0 + np.cos(2.0 * np.pi * x[_MODE_T] / c.push_sweep_period))
            target, lead = turn(seen, np.array([0.0, 0.0, 1.0]), swing), x[_LEAD]
        elif mode == BACKOFF:
            target, lead = x[_H], -c.backoff_lead
        else:
            base = x[_BASE] / np.linalg.norm(x[_BASE])
            e1 = np.cross([0.0, 0.0, 1.0], base)
            e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.array([1.0, 0, 0])
            e2 = np.cross(base, e1)
            phase = 2.0 * np.pi * x[_MODE_T] / c.search_period
            a = np.radians(c.search_cone_deg)
            target = np.cos(a) * base + np.sin(a) * (x[_SIDE] * np.cos(phase) * e1
                                                     + np.sin(phase) * e2)
            lead = c.search_lead
        h = x[_H] + (target - x[_H]) * min(1.0, dt / c.heading_time)
        if np.linalg.norm(h) < 1e-6:
            h = z_W
        h = lead_at_most(h / np.linalg.norm(h), z_W, np.radians(c.max_lead_deg))
        h = limit_pitch(h, np.radians(c.max_pitch_deg))
        x[_H] = h

        # The EPM over the point `lead` heights ahead of the capsule's magnet, moving at most
        # max_epm_speed.
        height = max(float(x[2] - p_WM[2]), 0.0)
        xy = p_WM[:2] + lead * height * horizontal(h)[:2]
        move = xy - x[0:2]
        reach = c.max_epm_speed * dt
        if np.linalg.norm(move) > reach:
            xy = x[0:2] + move * (reach / np.linalg.norm(move))
        x[_CMD] = self.command_for(xy, h, p_WM)
        discrete_state.set_value(self._state, x)


class LumenRayFromPoint(LeafSystem):
    """A world point on the lumen (the lumen truth's `lumen_point_W`) as a unit ray in the
    capsule camera's frame; visible when the point is finite and in front of the lens's
    field (`max_theta`), whether or not tissue hides it.

    .. pydrake_system::

        name: LumenRayFromPoint
        input_ports:
        - capsule_pose
        - point_W
        output_ports:
        - ray
        - visible

    capsule_pose: [q_WB wxyz, p_WB]. point_W: [x, y, z, ...] (only the first three are read).

    Args:
        X_BC: the camera's pose in the capsule body.
        max_theta: half field of view (rad).
    """

    def __init__(self, X_BC, max_theta: float = np.pi / 2):
        super().__init__()
        self._X_BC = X_BC
        self._cos = np.cos(max_theta)
        self._pose = self.DeclareVectorInputPort("capsule_pose", 7)
        self._point = self.DeclareVectorInputPort("point_W", 4)
        self.DeclareVectorOutputPort("ray", 3, lambda c, o: o.SetFromVector(self._ray(c)[0]))
        self.DeclareVectorOutputPort(
            "visible", 1, lambda c, o: o.SetAtIndex(0, 1.0 if self._ray(c)[1] else 0.0))

    def _ray(self, context):
        pose = np.asarray(self._pose.Eval(context), dtype=float)
        point = np.asarray(self._point.Eval(context), dtype=float)[:3]
        if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(point))):
            return np.zeros(3), False
        R_WB = Quaternion(pose[:4] / np.linalg.norm(pose[:4])).rotation()
        R_WC = R_WB @ self._X_BC.rotation().matrix()
        p_WC = pose[4:7] + R_WB @ self._X_BC.translation()
        r = R_WC.T @ (point - p_WC)
        if np.linalg.norm(r) < 1e-9:
            return np.zeros(3), False
        r = r / np.linalg.norm(r)
        return r, bool(r[2] >= self._cos)


def add_lumen_follower(builder, station, scenario, config: LumenFollowerConfig,
                       lumen: str = "truth", name: str = "lumen_follower") -> LumenFollower:
    """Adds a LumenFollower to `builder` (which holds `station`) and wires it: the capsule's
    pose from `capsule.state`, the lumen from the station, its command to `epm.command`.

    The station must be built with `external_epm_command=True` and a capsule camera.
    lumen: "truth" (the lumen truth's pixel through the lens, with its visibility, which
    accounts for tissue hiding the lumen), "truth_point" (the lumen truth's world point as a
    ray, seen whenever it is in front of the lens, even behind a fold) or "detected" (the
    lumen tracker's ray and visibility; needs `capsule.lumen_tracker`).
    """
    # Imported here: station imports much of the package.
    from capsule_drake.station import colon_for
    from capsule_drake.systems.epm_arm import EpmGuard
    from capsule_drake.teleop.operator import LumenRayFromTruth

    if lumen not in LUMEN_SOURCES:
        raise ValueError(f"lumen source {lumen!r} is not one of {LUMEN_SOURCES}")
    if scenario.capsule.camera is None:
        raise ValueError("the lumen follower needs capsule.camera (it follows the lumen seen)")
    if lumen == "detected" and scenario.capsule.lumen_tracker is None:
        raise ValueError("lumen 'detected' needs capsule.lumen_tracker")
    plant = station.GetSubsystemByName("plant")
    capsule = plant.GetModelInstanceByName("capsule")
    X_BC = plant.GetFrameByName("camera", capsule).GetFixedPoseInBodyFrame()
    p_BM = plant.GetFrameByName("ipm", capsule).GetFixedPoseInBodyFrame().translation()
    colon = colon_for(scenario)
    guard = EpmGuard(colon.abdomen, scenario.epm.magnet, scenario.epm.clearance,
                     np.zeros(3), np.inf)
    follower = builder.AddNamedSystem(name, LumenFollower(
        config, X_BC, p_BM, guard.lowest_centre_height))
    pose = builder.AddNamedSystem(f"{name}.pose", Demultiplexer([7, 6]))
    builder.Connect(station.GetOutputPort("capsule.state"), pose.get_input_port())
    builder.Connect(pose.get_output_port(0), follower.GetInputPort("capsule_pose"))
    if lumen == "truth":
        camera = station.GetSubsystemByName("capsule.camera")
        seen = builder.AddNamedSystem(f"{name}.lumen_seen", LumenRayFromTruth(camera.lens))
        builder.Connect(station.GetOutputPort("capsule.lumen.lumen_pixel"),
                        seen.GetInputPort("pixel"))
        builder.Connect(station.GetOutputPort("capsule.lumen.lumen_visible"),
                        seen.GetInputPort("visible"))
        ray, visible = seen.GetOutputPort("ray"), seen.GetOutputPort("visible")
    elif lumen == "truth_point":
        camera = station.GetSubsystemByName("capsule.camera")
        seen = builder.AddNamedSystem(f"{name}.lumen_seen",
                                      LumenRayFromPoint(X_BC, camera.lens.max_theta))
        builder.Connect(pose.get_output_port(0), seen.GetInputPort("capsule_pose"))
        builder.Connect(station.GetOutputPort("capsule.lumen.lumen_point_W"),
                        seen.GetInputPort("point_W"))
        ray, visible = seen.GetOutputPort("ray"), seen.GetOutputPort("visible")
    else:
        ray = station.GetOutputPort("capsule.lumen_tracker.lumen_ray")
        visible = station.GetOutputPort("capsule.lumen_tracker.lumen_visible")
    builder.Connect(ray, follower.GetInputPort("lumen_ray"))
    builder.Connect(visible, follower.GetInputPort("lumen_visible"))
    builder.Connect(follower.GetOutputPort("epm_command"), station.GetInputPort("epm.command"))
    return follower
