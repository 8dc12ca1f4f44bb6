"""Autonomous lumen following: the EPM moved so the capsule advances down the lumen.

`LumenFollower` is the robot's controller in place of the operator's hand. It sees what the
capsule's camera shows of the lumen (a ray in the camera frame and whether the lumen is in
view: from the lumen tracker, or from the lumen truth) and where the capsule is (its pose,
as an external localisation would give it); it knows the patient's skin (a body scan), so
that it keeps the magnet at its clearance. It knows nothing else of the colon.

The control law, every `period`:
- Heading h: the lumen direction in the world (the ray turned by the camera's orientation),
  low-passed, kept within `max_lead_deg` of the capsule's axis (a capsule the tissue holds
  back cannot wind up a large turn) and within `max_pitch_deg` of the horizontal. Where
  the lumen is steeper than that (a flexure that climbs), its horizontal direction is
  unreliable; the clipped heading turns it toward the way forward's, the more the steeper
  (`limit_pitch`). (Keeping the lumen's own, a lumen 82-85 deg up with a horizontal part
  of a few per cent sideways gave a heading 60 deg up and 55 deg off the colon's axis, into
  the wall of seed 7's splenic flexure, where the capsule stayed for 500 s.)
- Force, not position: the EPM goes where the magnet's pull on the capsule plus the
  capsule's weight is a drive force f along h (`epm_pose_for_force`): the pull carries
  the weight and leaves f to move the capsule, which floats in the insufflated lumen
  instead of being pinned to a wall. Its moment is turned so that its field at the
  capsule's magnet points along h (`field_aligning_moment_direction`), so the capsule
  also turns toward the lumen. The controller knows the two magnets' moments and the
  capsule's weight (the hardware's data), and nothing of the colon but the patient's skin
  (a body scan): the EPM stays `height_margin` above its clearance floor; where the force
  wanted would need it lower (a strong lift), it stays on the floor.
  Holding the capsule up with the EPM low against the skin (as a position law does) pins
  it to the top wall with 10-30 times its weight, where the haustral folds stop it; the
  lumen's drop at the hepatic flexure then cannot be followed, because only gravity can
  take the capsule down. With the force law, f sets the pull: ~0.03 N moves the capsule at
  1 cm/s against the colon's resistance, and the EPM sits 20-25 cm above it.
- Speed: f grows while the capsule moves slower than `target_speed` along h and
  shrinks while it moves faster (quickly above `overspeed` times the target); the command
  moves at most `max_epm_speed`, so a capsule that breaks free does not drag the EPM on.
- Stall: with f at its largest and no progress for `stall_after`, push: f sweeps between
  `push_force` and `push_force_low` and the heading wiggles sideways (the lumen may
  swing out of view meanwhile; the push goes on); if the capsule still does not move
  within `push_time`, back off (f = `backoff_force` backward, for `backoff_time`), then
  search if the lumen is out of view, and retry.
- Lumen lost (not seen for `lost_after`): coast (f = `coast_force` on along the heading
  held, for `coast_time`: in a bend the lumen goes out of sight behind the wall and comes
  back round it), then search: the heading sweeps a cone around the last forward direction
  the lumen was seen in with f = `search_force`; then coast again. When it is seen again,
  go on. (Backing off when the lumen is lost, the first design, returned the capsule to
  where the lumen was in view, from which it drove into the same bend again: 5 of 10
  colons held in the sigmoid's hairpins.)
- Sense of direction: the controller drops breadcrumbs along the capsule's path (its own
  memory of the poses it was given), on new ground only. It follows where along its trail
  the capsule is from update to update (the nearest crumb within `trail_reach` of trail of
  where it was, not the nearest anywhere: in the sigmoid's hairpins the trail's other limb
  lies just beyond the wall). A capsule that slides or backs off along the way it came is
  retracing: it drops no crumbs (which would turn its sense of direction round) and the way
  forward stays along the trail toward its newest crumb. A lumen direction that heads into
  crumbs older than the one the capsule is at, or, while retracing, against the way
  forward, is the way out (the capsule has turned back, or the truth's "ahead" flipped with
  the camera): ignored, and the search turns toward the way forward (along the crumbs from
  older to newer around the capsule). This holds in the sigmoid's hairpins, where the way
  forward does point back across the abdomen.

A non-finite capsule pose holds the command; a non-finite lumen ray counts as not seen.
"""

import dataclasses

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.primitives import Demultiplexer

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.control.analysis import epm_pose_for_force
from capsule_drake.epm.poses import field_aligning_moment_direction
from capsule_drake.perception.lumen_truth import add_lumen_ray_from_truth
from capsule_drake.blocks import block, checked, need
from capsule_drake.schema import need_range
from capsule_drake.teleop.mapping import lead_at_most, limit_pitch, turn

LUMEN_SOURCES = ("truth", "truth_point", "detected")
POSE_SOURCES = ("truth", "sensors")

# Modes of the controller (the `status` output's first element).
CRUISE, PUSH, BACKOFF, SEARCH, COAST = 0.0, 1.0, 2.0, 3.0, 4.0


@dataclasses.dataclass
class LumenFollowerConfig:
    """How the autonomous controller drives the EPM. YAML-loadable; all fields default."""

    # Update period of the controller (s).
    period: float = 0.05
    # Speed the capsule is driven at along its heading (m/s).
    target_speed: float = 0.01
    # The drive force f (N): the magnet's pull plus the capsule's weight, along the heading.
    # Rate at which f grows per unit of speed shortfall (N per m/s, per s).
    force_gain: float = 2.0
    # Smallest and largest f in cruise (N; the capsule weighs 0.12 N).
    min_force: float = 0.01
    max_force: float = 0.12
    # Above overspeed * target_speed, f shrinks at brake_rate (N/s).
    overspeed: float = 2.0
    brake_rate: float = 0.05
    # Time constant of the capsule's speed estimate (s).
    speed_time: float = 1.0
    # Share of the capsule's weight the pull carries (1: it floats; below 1 the rest
    # presses it on the tissue below, where friction resists its motion).
    lift: float = 1.0
    # Largest share of the capsule's weight the pull's vertical part may carry, whatever the
    # heading: the lift plus the drive's vertical part on a climbing heading is cut to it.
    # Past 1 the capsule leaves the tissue below for the unstable hold under the magnet
    # (read on population patients 1015 and 1028: docs/results/navigation.md). 10: no cap,
    # as the follower was made and benchmarked.
    max_lift: float = 10.0
    # Time constant with which the heading follows the lumen direction (s).
    heading_time: float = 0.5
    # The heading stays within this angle of the capsule's axis (deg) and of the
    # horizontal (deg).
    max_lead_deg: float = 40.0
    max_pitch_deg: float = 60.0
    # Least height of the EPM's centre above the lowest its clearance from the skin allows (m).
    height_margin: float = 0.0
    # Fastest the EPM's commanded position moves over the patient (m/s).
    max_epm_speed: float = 0.03
    # Stall: f at >= 90 % of max_force and speed below stall_speed_fraction *
    # target_speed for stall_after (s) -> push.
    stall_speed_fraction: float = 0.2
    stall_after: float = 6.0
    # Push: f sweeps from push_force down to push_force_low and back once per
    # push_sweep_period (s), for push_time (s), while the heading wiggles sideways (deg,
    # period s); progress along the heading of unstick_distance (m) counts as unstuck.
    push_force: float = 0.2
    push_force_low: float = 0.0
    push_sweep_period: float = 12.0
    push_time: float = 12.0
    wiggle_deg: float = 25.0
    wiggle_period: float = 4.0
    unstick_distance: float = 0.01
    # Back off: f = backoff_force (N) backward along the heading, for backoff_time (s).
    backoff_force: float = 0.03
    backoff_time: float = 3.0
    # Coast: f = coast_force (N) on along the heading held, for coast_time (s).
    coast_force: float = 0.03
    coast_time: float = 3.0
    # Lumen not seen for lost_after (s) -> coast, then search: the heading sweeps a cone
    # of half-angle search_cone_deg (deg) once per search_period (s) with f =
    # search_force (N); after search_time (s) without the lumen, coast again.
    lost_after: float = 1.0
    search_cone_deg: float = 35.0
    search_period: float = 8.0
    search_force: float = 0.01
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
    # Where along its trail the capsule is: the crumb nearest it among those within
    # trail_reach (m, of trail) of the one it was at; farther than trail_radius (m, about a
    # lumen's width) from all of them, it is on new ground.
    trail_reach: float = 0.05
    trail_radius: float = 0.05


def check_lumen_follower_config(config: LumenFollowerConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.period, "control.period", ">= 0.0001", "s")
    for name, unit in (("speed_time", "s"), ("heading_time", "s"), ("wiggle_period", "s"),
                       ("search_period", "s"), ("max_epm_speed", "m/s"),
                       ("target_speed", "m/s"), ("crumb_spacing", "m"), ("look_ahead", "m"),
                       ("crumb_radius", "m"), ("trail_reach", "m"), ("trail_radius", "m")):
        need_range(getattr(config, name), f"control.{name}", "> 0", unit)
    for name, unit in (("force_gain", ""), ("brake_rate", "N/s"), ("height_margin", "m"),
                       ("stall_speed_fraction", ""), ("stall_after", "s"), ("push_time", "s"),
                       ("wiggle_deg", "deg"), ("unstick_distance", "m"),
                       ("backoff_time", "s"), ("coast_time", "s"), ("lost_after", "s"),
                       ("search_time", "s")):
        need_range(getattr(config, name), f"control.{name}", ">= 0", unit)
    for name in ("min_force", "backoff_force", "coast_force", "search_force"):
        need_range(getattr(config, name), f"control.{name}", "> 0", "N")
    need_range(config.lift, "control.lift", "[0, 1]")
    need_range(config.max_lift, "control.max_lift", "[0, 10]")
    if not config.max_lift >= config.lift:
        raise ValueError(f"control.max_lift must be >= control.lift ({config.lift}), got "
                         f"{config.max_lift}")
    if not config.max_force >= config.min_force:
        raise ValueError("lumen follower max_force must be >= min_force")
    need_range(config.push_force_low, "control.push_force_low", ">= 0", "N")
    if not config.push_force >= config.push_force_low:
        raise ValueError("lumen follower needs push_force >= push_force_low >= 0")
    need_range(config.push_sweep_period, "control.push_sweep_period", "> 0", "s")
    need_range(config.max_crumbs, "control.max_crumbs", "[3, 10000]", "",
               "3 numbers of state each")
    need_range(config.overspeed, "control.overspeed", "> 1")
    for name in ("max_lead_deg", "max_pitch_deg", "search_cone_deg"):
        need_range(getattr(config, name), f"control.{name}", "[0, 90]", "deg")


# Layout of the discrete state.
_CMD = slice(0, 6)      # the EPM command [p_WE, m_hat_W]
_H = slice(6, 9)        # heading (world, unit)
_F = 9                  # drive force f (N)
_NCRUMB = 10            # number of breadcrumbs
_K = 11                 # index of the crumb the capsule is at
# 12: unused
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


class LumenFollowerController(LeafSystem):
    """Lumen ray + capsule pose -> EPM command [p_WE, m_hat_W] (module docstring).

    .. pydrake_system::

        name: LumenFollowerController
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
    status: [mode (0 cruise, 1 push, 2 back off, 3 search, 4 coast), drive force f (N, along the
    heading; negative backing off), speed along the heading (m/s), time since the lumen
    was seen (s)].

    Args:
        config: LumenFollowerConfig.
        X_BC: the camera's pose in the capsule body (RigidTransform).
        p_BM: the capsule magnet's position in the body (where the field is aimed).
        floor: function (x, y, m_hat) -> lowest allowed EPM centre height (e.g.
            `EpmGuard.lowest_centre_height`).
        epm_moment, ipm_moment: the magnets' dipole moments (A m^2).
        weight: the capsule's weight (N).
    """

    def __init__(self, config: LumenFollowerConfig, X_BC, p_BM, floor, epm_moment: float,
                 ipm_moment: float, weight: float):
        super().__init__()
        check_lumen_follower_config(config)
        for name, value in (("epm_moment", epm_moment), ("ipm_moment", ipm_moment),
                            ("weight", weight)):
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"lumen follower {name} must be > 0, got {value}")
        self._config = config
        self._moments = (float(epm_moment), float(ipm_moment))
        self._weight = float(weight)
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

    @property
    def config(self) -> LumenFollowerConfig:
        """The control law's gains, limits and timings (as the scenario gave them)."""
        return self._config

    def command_for(self, drive, heading, p_WM, previous=None):
        """[p_WE, m_hat_W]: the EPM where its pull on the capsule's magnet at p_WM plus the
        capsule's weight is `drive` newtons along `heading`, at least `height_margin` above
        its floor, moved from `previous` (a command) by at most max_epm_speed * period; its
        moment aligns the field at the magnet with `heading`."""
        c = self._config
        force = drive * heading + np.array([0.0, 0.0, c.lift * self._weight])
        force[2] = min(force[2], c.max_lift * self._weight)
        p, m, _ = epm_pose_for_force(p_WM, heading, force, *self._moments)
        if previous is not None:
            move = p - previous[:3]
            reach = c.max_epm_speed * c.period
            if np.linalg.norm(move) > reach:
                p = previous[:3] + move * (reach / np.linalg.norm(move))
        for _ in range(2):  # the floor depends a little on the moment's tilt
            p[2] = max(p[2], self._floor(p[0], p[1], m) + c.height_margin)
            u = p_WM - p
            m = field_aligning_moment_direction(u / np.linalg.norm(u), heading)
        # On the floor of the moment it is sent with (the last turn may tilt it past the
        # floor it was raised to: the guard would raise it, and count it).
        p[2] = max(p[2], self._floor(p[0], p[1], m) + c.height_margin)
        return np.concatenate([p, m])

    def _place_on_trail(self, x, crumbs, p):
        """Where along its trail the capsule at p is: (number of crumbs, index of its
        crumb), updated in x. The crumb is the nearest among those within trail_reach of
        trail of the last one. A capsule at the newest crumb, or farther than trail_radius
        from those, that has moved crumb_spacing from the newest, within 72 deg of the
        trail's last direction (on, round a bend as tight as the colon's; not back, nor
        across the lumen: a slip), is on new ground and drops a crumb (the oldest goes when
        the trail is full)."""
        c = self._config
        n, k = int(x[_NCRUMB]), int(x[_K])
        reach = int(np.ceil(c.trail_reach / c.crumb_spacing))
        lo, hi = max(0, k - reach), min(n, k + reach + 1)
        distance = np.linalg.norm(crumbs[lo:hi] - p, axis=1)
        j = int(np.argmin(distance))
        k = lo + j if distance[j] <= c.trail_radius else n - 1
        step = p - crumbs[n - 1]
        last = crumbs[n - 1] - crumbs[n - 2]
        onward = step @ last > 0.3 * np.linalg.norm(step) * np.linalg.norm(last)
        if k == n - 1 and onward and np.linalg.norm(step) > c.crumb_spacing:
            if n == len(crumbs):
                crumbs[:-1] = crumbs[1:].copy()
                n -= 1
            crumbs[n] = p
            n += 1
            k = n - 1
        x[_NCRUMB], x[_K] = n, k
        return n, k

    def _calc_status(self, context, output):
        x = context.get_discrete_state(self._state).value()
        output.SetFromVector([x[_MODE], x[_F], x[_V], x[_LOST_T]])

    def _pose_of(self, context):
        pose = np.asarray(self._pose.Eval(context), dtype=float)
        if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:4]) < 1e-6:
            return None
        R_WB = rotation_from_quaternion(pose[:4])
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
        x[_K] = 2.0
        x[_PREV] = p
        x[_WAY] = z_W
        x[_SIDE] = 1.0
        x[_INIT] = 1.0
        x[_F] = self._config.min_force
        x[_CMD] = self.command_for(x[_F], z_W, p_WM)

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

        # Sense of direction: breadcrumbs, the crumb the capsule is at, the way forward.
        crumbs = x[_CRUMBS:].reshape(-1, 3)
        n, k = self._place_on_trail(x, crumbs, p)
        trail = crumbs[:n]
        retracing = k < n - 3
        ahead = trail[min(k + 2, n - 1)] if k + 2 <= n - 1 else p
        w = ahead - trail[max(k - 2, 0)]
        if np.linalg.norm(w) > 0.5 * c.crumb_spacing:
            x[_WAY] = w / np.linalg.norm(w)
        way = x[_WAY].copy()
        older = trail[:max(k - 1, 0)]

        def backward(direction):
            """Whether `direction` heads into where the capsule came from."""
            if retracing and direction @ way < 0.0:
                return True
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

        def resume():
            """Back to cruise from the smallest force."""
            switch(CRUISE)
            x[_F] = c.min_force
            x[_STALL_T] = 0.0

        if mode == CRUISE:
            if lost:
                switch(COAST)
                x[_BASE] = forward_base()
            else:
                x[_F] += c.force_gain * (c.target_speed - x[_V]) * dt
                if x[_V] > c.overspeed * c.target_speed:
                    x[_F] -= c.brake_rate * dt
                x[_F] = np.clip(x[_F], c.min_force, c.max_force)
                stalled = (x[_F] >= 0.9 * c.max_force
                           and x[_V] < c.stall_speed_fraction * c.target_speed)
                x[_STALL_T] = x[_STALL_T] + dt if stalled else 0.0
                if x[_STALL_T] > c.stall_after:
                    switch(PUSH)
                    x[_ANCHOR] = p
                    x[_BASE] = seen
                    x[_STALL_T] = 0.0
        elif mode == PUSH:
            # The lumen lost during a push does not end it: the push's wiggle and its force
            # sweep move the view, and the lumen can go out of sight. (Ending it in a coast,
            # as at first, never reached the back off: a capsule held at the splenic
            # flexure went cruise, push, coast, search, cruise for 500 s.)
            if (p - x[_ANCHOR]) @ x[_BASE] > c.unstick_distance:
                switch(CRUISE)  # go on with the force that got it moving
                x[_F] = np.clip(x[_F], c.min_force, c.max_force)
            elif x[_MODE_T] > c.push_time:
                switch(BACKOFF)
                x[_BASE] = forward_base()
                x[_SIDE] = -x[_SIDE]
        elif mode == BACKOFF:
            if x[_MODE_T] > c.backoff_time:
                if x[_LOST_T] > 0.0:
                    switch(SEARCH)
                else:
                    resume()
        elif mode == COAST:
            if x[_LOST_T] == 0.0:
                resume()
            elif x[_MODE_T] > c.coast_time:
                switch(SEARCH)
        elif mode == SEARCH:
            if x[_LOST_T] == 0.0:
                resume()
            elif x[_MODE_T] > c.search_time:
                switch(COAST)
                x[_BASE] = way

        # The heading wanted and the drive force of the mode.
        mode = x[_MODE]
        if mode == CRUISE:
            target, drive = seen, x[_F]
        elif mode == PUSH:
            swing = x[_SIDE] * np.radians(c.wiggle_deg) * np.sin(
                2.0 * np.pi * x[_MODE_T] / c.wiggle_period)
            x[_F] = c.push_force_low + (c.push_force - c.push_force_low) * 0.5 * (
                1.0 + np.cos(2.0 * np.pi * x[_MODE_T] / c.push_sweep_period))
            target, drive = turn(seen, np.array([0.0, 0.0, 1.0]), swing), x[_F]
        elif mode == BACKOFF:
            target, drive = x[_H], -c.backoff_force
        elif mode == COAST:
            target, drive = x[_H], c.coast_force
        else:
            base = x[_BASE] / np.linalg.norm(x[_BASE])
            e1 = np.cross([0.0, 0.0, 1.0], base)
            e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.array([1.0, 0, 0])
            e2 = np.cross(base, e1)
            phase = 2.0 * np.pi * x[_MODE_T] / c.search_period
            a = np.radians(c.search_cone_deg)
            target = np.cos(a) * base + np.sin(a) * (x[_SIDE] * np.cos(phase) * e1
                                                     + np.sin(phase) * e2)
            drive = c.search_force
        h = x[_H] + (target - x[_H]) * min(1.0, dt / c.heading_time)
        if np.linalg.norm(h) < 1e-6:
            h = z_W
        h = lead_at_most(h / np.linalg.norm(h), z_W, np.radians(c.max_lead_deg))
        h = limit_pitch(h, np.radians(c.max_pitch_deg), toward=way)
        x[_H] = h

        # The EPM where the pull plus the weight is `drive` along h.
        if mode in (BACKOFF, SEARCH, COAST):
            x[_F] = drive  # reported in the status
        x[_CMD] = self.command_for(drive, h, p_WM, previous=x[_CMD])
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
        R_WB = rotation_from_quaternion(pose[:4])
        R_WC = R_WB @ self._X_BC.rotation().matrix()
        p_WC = pose[4:7] + R_WB @ self._X_BC.translation()
        r = R_WC.T @ (point - p_WC)
        if np.linalg.norm(r) < 1e-9:
            return np.zeros(3), False
        r = r / np.linalg.norm(r)
        return r, bool(r[2] >= self._cos)


@dataclasses.dataclass
class LumenFollower:
    """The autonomous lumen follower drives the EPM (module docstring): it sees the lumen in
    the capsule's camera and knows the capsule's pose, the magnets' moments, the capsule's
    weight and the patient's skin."""

    # Where it sees the lumen: "truth" (the lumen truth's pixel through the lens, with its
    # visibility, which accounts for tissue hiding the lumen), "truth_point" (the lumen
    # truth's world point as a ray, seen whenever it is in front of the lens, even behind a
    # fold) or "detected" (the lumen tracker's; needs capsule.lumen_tracker).
    lumen: str = "truth"
    # Where it knows the capsule's pose from: "truth" (the simulation) or "sensors" (the
    # capsule's own estimate, capsule.localizer: its Hall sensors, IMU and the EPM's pose,
    # from the capsule's known start).
    pose: str = "truth"
    # The control law's gains, limits and timings.
    control: LumenFollowerConfig = dataclasses.field(default_factory=LumenFollowerConfig)


def check_lumen_follower(config: LumenFollower) -> None:
    """Raises ValueError naming the first impossible field (on its own; what it needs of
    the rest of the scenario is checked with the scenario)."""
    if config.lumen not in LUMEN_SOURCES:
        raise ValueError(f"lumen must be one of {', '.join(LUMEN_SOURCES)}, got {config.lumen!r}")
    if config.pose not in POSE_SOURCES:
        raise ValueError(f"pose must be one of {', '.join(POSE_SOURCES)}, got {config.pose!r}")
    check_lumen_follower_config(config.control)


def check_lumen_follower_driver(driver: LumenFollower, scenario) -> None:
    checked("epm.driver (LumenFollower): ", check_lumen_follower, driver)
    capsule = scenario.capsule
    need(capsule.camera is not None,
         "epm.driver (LumenFollower) needs capsule.camera (it follows the lumen seen)")
    need(driver.lumen != "detected" or capsule.lumen_tracker is not None,
         "epm.driver (LumenFollower) lumen detected needs capsule.lumen_tracker")
    need(driver.pose != "sensors" or capsule.localizer is not None,
         "epm.driver (LumenFollower) pose sensors needs capsule.localizer (with "
         "capsule.imu and capsule.magnetic_array)")


@block("epm.driver", LumenFollower, check=check_lumen_follower_driver)
def add_lumen_follower(builder, parts, config: LumenFollower,
                       name: str = "lumen_follower") -> LumenFollowerController:
    """`lumen_follower` and what it reads: the capsule's pose (the truth, or
    capsule.localizer's estimate), the lumen (`<name>.lumen_seen` from the truth, or the
    tracker's); its command goes to the EPM's carrier and is exported as epm.command, its
    heading and status as `<name>.heading` and `<name>.status`."""
    magnet = parts.epm.magnet
    follower = builder.AddNamedSystem(name, LumenFollowerController(
        config.control, parts.capsule.X_BC, parts.capsule.X_BM.translation(),
        parts.epm.guard.lowest_centre_height, magnet.moment(), parts.ipm.moment(),
        parts.capsule.mass * parts.gravity))
    demux = builder.AddNamedSystem(f"{name}.pose", Demultiplexer([7, 6]))
    builder.Connect(parts.capsule_state, demux.get_input_port())
    pose_port = demux.get_output_port(0)
    if config.pose == "sensors":   # the capsule's own estimate (navigation/localization.py)
        pose_port = parts.output("capsule.localizer.pose")
    builder.Connect(pose_port, follower.GetInputPort("capsule_pose"))
    if config.lumen == "truth":
        seen = add_lumen_ray_from_truth(builder, parts, f"{name}.lumen_seen")
        ray, visible = seen.GetOutputPort("ray"), seen.GetOutputPort("visible")
    elif config.lumen == "truth_point":
        seen = builder.AddNamedSystem(f"{name}.lumen_seen", LumenRayFromPoint(
            parts.capsule.X_BC, parts.shared("capsule.camera.lens").max_theta))
        # The ray as the camera sees it: from the capsule's true pose.
        builder.Connect(demux.get_output_port(0), seen.GetInputPort("capsule_pose"))
        builder.Connect(parts.output("capsule.lumen.lumen_point_W"),
                        seen.GetInputPort("point_W"))
        ray, visible = seen.GetOutputPort("ray"), seen.GetOutputPort("visible")
    else:
        ray = parts.output("capsule.lumen_tracker.lumen_ray")
        visible = parts.output("capsule.lumen_tracker.lumen_visible")
    builder.Connect(ray, follower.GetInputPort("lumen_ray"))
    builder.Connect(visible, follower.GetInputPort("lumen_visible"))
    command = follower.GetOutputPort("epm_command")
    builder.Connect(command, parts.epm.command_input(builder, parts))
    parts.export(command, "epm.command")
    parts.export_outputs(follower, name, ("heading", "status"))
    return follower
