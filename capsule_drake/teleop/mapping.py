"""Master-to-slave mapping: stylus motion to an EPM pose command.

The capsule's three motions of the seed paper, as the operator sees them in the camera
image: forward and backward (push the stylus away from you / pull it back), yaw (stylus
right / left) and pitch (stylus up / down). The EPM moves over the patient along the
capsule's heading; its moment is turned so that its field at the capsule points along the
commanded heading (docs/sources.md section 1: m ~ (3/2 u u^T - I) h), which turns the capsule's
magnet, and with it the capsule. The EPM rides at its clearance above the skin (the arm's
guard would raise it anyway), plus a height the operator does not control.

Position mode (default): the stylus's travel toward / away from the operator moves the EPM
(scaled) along the commanded heading; its sideways and vertical displacement since the
clutch was last released turns the heading (yaw, pitch) from what it was then, about the
image's axes. Lead mode: everything relative to the capsule as the camera shows it: the
stylus's travel sets how far the EPM leads the capsule along the heading (up to
`max_lead_distance`), the EPM staying over the capsule as it moves (hold the stylus forward
and the magnet keeps pulling), and its sideways and vertical displacement turn the heading
from the camera's current axis (hold it right and the capsule keeps turning right; centre
it and the capsule holds its direction). Rate mode: the
stylus's offset from the workspace centre sets the EPM's speed and the heading's turn
rates. Either way the heading leads the capsule's current axis by
at most `max_lead_deg`, so a capsule the lumen holds back cannot wind up a large error.
The clutch button (held) decouples the stylus for indexing. A lost or stale link, or a
non-finite stylus, holds the command; the next valid sample re-references (no jump).
"""

import dataclasses

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.epm.poses import field_aligning_moment_direction
from capsule_drake.schema import need_range

MODES = ("position", "lead", "rate")


@dataclasses.dataclass
class MappingConfig:
    """How the stylus drives the EPM. YAML-loadable; all fields default."""

    # "position", "lead" or "rate" (see the module docstring).
    mode: str = "position"
    # Position mode: EPM travel per stylus travel along the heading (m/m), and heading turn
    # per stylus travel sideways (yaw) and up/down (pitch) (rad/m).
    translation_scale: float = 2.0
    yaw_gain: float = 12.0
    pitch_gain: float = 12.0
    # Rate mode: EPM speed per stylus offset (m/s per m), turn rates per offset (rad/s per
    # m), and a dead band around the centre (m).
    rate_translation: float = 0.5
    rate_yaw: float = 10.0
    rate_pitch: float = 10.0
    dead_band: float = 0.005
    # The commanded heading stays within this angle of the horizontal (deg), and within
    # max_lead_deg of the capsule's current axis.
    max_pitch_deg: float = 45.0
    max_lead_deg: float = 40.0
    # Lead mode: the EPM's farthest lead ahead of (or behind) the capsule (m).
    max_lead_distance: float = 0.05
    # Shared control: the EPM's forward travel (or lead) goes toward the lumen the tracker
    # detects, when it sees one, instead of along the commanded heading. In the lead mode,
    # with the free range along the lumen ray known (`lumen_range`, from the depth image),
    # the EPM goes over the point that far along the ray, at most the range less
    # `assist_margin`: the capsule is pulled toward open lumen, never into the tissue
    # beyond it.
    assist: bool = False
    assist_margin: float = 0.01
    # The EPM's command moves over the patient at most this fast (m/s; 0: no limit). In the
    # lead mode this also keeps a capsule that breaks free from dragging the EPM after it.
    max_speed: float = 0.0
    # Update period (s).
    period: float = 0.005
    # A stylus sample older than this (s; from the channel's `age`) counts as a lost link.
    stale_after: float = 0.1


def check_mapping_config(config: MappingConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    if config.mode not in MODES:
        raise ValueError(f"teleop mapping mode {config.mode!r} is not one of {MODES}")
    for name, unit in (("translation_scale", "m/m"), ("yaw_gain", "rad/m"),
                       ("pitch_gain", "rad/m"), ("rate_translation", "m/s per m"),
                       ("rate_yaw", "rad/s per m"), ("rate_pitch", "rad/s per m"),
                       ("dead_band", "m"), ("max_pitch_deg", "deg"), ("max_lead_deg", "deg"),
                       ("max_lead_distance", "m"), ("assist_margin", "m"),
                       ("max_speed", "m/s")):
        need_range(getattr(config, name), f"mapping.{name}", ">= 0", unit)
    need_range(config.period, "mapping.period", "> 0", "s")
    need_range(config.stale_after, "mapping.stale_after", "> 0", "s")


def turn(h, axis, angle):
    """h rotated by `angle` about the unit `axis` (Rodrigues)."""
    axis = np.asarray(axis, dtype=float)
    return (h * np.cos(angle) + np.cross(axis, h) * np.sin(angle)
            + axis * (axis @ h) * (1.0 - np.cos(angle)))


def limit_pitch(h, max_pitch: float, toward=None):
    """h with its elevation above the horizontal clipped to +-max_pitch (rad).

    The clipped heading keeps h's horizontal direction. That direction is ill-defined as h
    nears the vertical (a lumen straight up: its few per cent of horizontal part is noise,
    which the clip would blow up to a full cos(max_pitch) sideways). With `toward` (a
    direction whose horizontal part is trusted, e.g. the way the capsule has come), the
    horizontal direction is h's plus toward's horizontal unit vector times what h lacks of
    cos(max_pitch): h's own at the limit, toward's at the vertical, continuous between."""
    h = np.asarray(h, dtype=float) / np.linalg.norm(h)
    horizontal = np.hypot(h[0], h[1])
    elevation = np.arctan2(h[2], horizontal)
    if abs(elevation) <= max_pitch:
        return h
    flat = h[:2].copy()
    way = np.zeros(2) if toward is None else np.asarray(toward[:2], dtype=float)
    if np.hypot(*way) > 1e-9:
        flat = flat + (np.cos(max_pitch) - horizontal) * (way / np.hypot(*way))
    if np.linalg.norm(flat) < 1e-9:
        return h
    e = np.clip(elevation, -max_pitch, max_pitch)
    flat = flat / np.linalg.norm(flat) * np.cos(e)
    return np.array([flat[0], flat[1], np.sin(e)])


def lead_at_most(h, axis, max_angle: float):
    """h turned toward `axis` until it is at most `max_angle` (rad) from it."""
    h = h / np.linalg.norm(h)
    axis = axis / np.linalg.norm(axis)
    angle = np.arccos(np.clip(h @ axis, -1.0, 1.0))
    if angle <= max_angle:
        return h
    normal = np.cross(axis, h)
    if np.linalg.norm(normal) < 1e-12:
        return axis
    return turn(axis, normal / np.linalg.norm(normal), max_angle)


def horizontal(h):
    """The horizontal unit vector nearest h (x if h is vertical)."""
    flat = np.array([h[0], h[1], 0.0])
    norm = np.linalg.norm(flat)
    return flat / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])


class TeleopMapping(LeafSystem):
    """Stylus -> EPM pose command [p_WE, m_hat_W] (module docstring).

    .. pydrake_system::

        name: TeleopMapping
        input_ports:
        - stylus
        - stylus_age (optional)
        - link_ok (optional)
        - lumen_ray (optional)
        - lumen_visible (optional)
        - lumen_range (optional)
        - capsule_state
        output_ports:
        - epm_command
        - heading

    stylus: [p_D (3), quaternion (4), clutch, mode] from the device (through the channel).
    stylus_age: how old that sample is (s); unconnected: fresh. link_ok: the device's link
    (0: lost, hold the command); unconnected: up. lumen_ray, lumen_visible: the lumen
    tracker's, for `assist`; lumen_range: the free range along that ray (m; NaN:
    unknown; systems/lumen_range.py). capsule_state: [q wxyz,
    p_WB, w, v] of the capsule (the pose the operator's camera image shows; the capsule's
    position locates the field). epm_command: the EPM's centre and moment direction.
    heading: the commanded heading h_W (unit) of the capsule.

    Args:
        config: MappingConfig.
        X_BC: camera pose in the capsule body (its axes define right, down, forward).
        p_BM: the capsule magnet's position in the body (where the field is aimed).
        floor: function (x, y, m_hat) -> lowest allowed EPM centre height (e.g.
            `EpmGuard.lowest_centre_height`).
        initial_command: [p_WE, m_hat_W] to start from (the EPM's start pose).
        initial_heading: the capsule's starting heading h_W.
    """

    def __init__(self, config: MappingConfig, X_BC, p_BM, floor, initial_command,
                 initial_heading):
        super().__init__()
        check_mapping_config(config)
        self._config = config
        self._R_BC = np.asarray(X_BC.rotation().matrix())
        self._p_BM = np.asarray(p_BM, dtype=float)
        self._floor = floor
        self._stylus = self.DeclareVectorInputPort("stylus", 9)
        self._age = self.DeclareVectorInputPort("stylus_age", 1)
        self._link = self.DeclareVectorInputPort("link_ok", 1)
        self._lumen_ray = self.DeclareVectorInputPort("lumen_ray", 3)
        self._lumen_visible = self.DeclareVectorInputPort("lumen_visible", 1)
        self._lumen_range = self.DeclareVectorInputPort("lumen_range", 1)
        self._capsule = self.DeclareVectorInputPort("capsule_state", 13)
        command = np.asarray(initial_command, dtype=float)
        h0 = np.asarray(initial_heading, dtype=float)
        height = command[2] - floor(command[0], command[1], command[3:])
        # [engaged, stylus at engagement (3), image right at engagement (3), heading at
        #  engagement (3), command (6), heading (3), height above floor, stylus at the
        #  previous sample (3), image up at engagement (3), lead (lead mode)]
        initial = np.concatenate([[0.0], np.zeros(3), command[:3], h0, command, h0,
                                  [max(height, 0.0)], np.zeros(6), [0.0]])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort(
            "epm_command", 6,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[10:16]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "heading", 3,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[16:19]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

    def _camera_pose(self, state):
        """R_WC of the capsule's camera and the capsule magnet's position p_WM."""
        q = np.asarray(state[:4], dtype=float)
        R_WB = rotation_from_quaternion(q)
        return R_WB @ self._R_BC, np.asarray(state[4:7]) + R_WB @ self._p_BM

    def command_for(self, p_WE_xy, heading, p_WM, height):
        """[p_WE, m_hat_W]: the EPM over (x, y) at `height` above its floor, its moment
        aligning the field at the capsule's magnet with `heading`."""
        p = np.array([p_WE_xy[0], p_WE_xy[1], 0.0])
        m = np.array([0.0, 0.0, 1.0])
        for _ in range(2):  # the floor depends a little on the moment's tilt
            p[2] = self._floor(p[0], p[1], m) + height
            u = p_WM - p
            m = field_aligning_moment_direction(u / np.linalg.norm(u), heading)
        return np.concatenate([p, m])

    def _update(self, context, discrete_state):
        c = self._config
        x = context.get_discrete_state(self._state).value().copy()
        stylus = np.asarray(self._stylus.Eval(context), dtype=float)
        age = float(self._age.Eval(context)[0]) if self._age.HasValue(context) else 0.0
        state = np.asarray(self._capsule.Eval(context), dtype=float)
        link_ok = (float(self._link.Eval(context)[0]) > 0.5 if self._link.HasValue(context)
                   else True)
        lost = (not link_ok or not np.all(np.isfinite(stylus)) or not np.isfinite(age)
                or age > c.stale_after or not np.all(np.isfinite(state)))
        clutch = stylus[7] > 0.5 if not lost else True
        if lost or clutch:
            x[0] = 0.0  # hold the command; re-reference on the next engaged sample
            discrete_state.set_value(self._state, x)
            return
        R_WC, p_WM = self._camera_pose(state)
        right, up, forward_axis = R_WC[:, 0], -R_WC[:, 1], R_WC[:, 2]
        p = stylus[:3]
        if x[0] < 0.5:  # engage: references from here
            x[0] = 1.0
            x[1:4] = p
            x[20:23] = p  # the stylus at the previous sample
            x[7:10] = x[16:19]  # the heading at engagement
            x[4:7], x[23:26] = right, up  # the image's axes at engagement
        if c.mode in ("position", "lead"):
            yaw, pitch = (p[:2] - x[1:3]) * [c.yaw_gain, c.pitch_gain]
            # Position: turned from the heading at engagement, about the image's axes then.
            # Lead: from the camera's current axis, as an endoscope's tip is steered from
            # its own view.
            h0, h_up, h_right = ((x[7:10], x[23:26], x[4:7]) if c.mode == "position"
                                 else (forward_axis, up, right))
            h = turn(turn(h0, h_up, -yaw), h_right, pitch)
            step = -(p[2] - x[22]) * c.translation_scale
        else:
            offset = np.where(np.abs(p) > c.dead_band, p - np.sign(p) * c.dead_band, 0.0)
            h = turn(turn(x[16:19], up, -offset[0] * c.rate_yaw * c.period), right,
                     offset[1] * c.rate_pitch * c.period)
            step = -offset[2] * c.rate_translation * c.period
        x[20:23] = p
        # The heading leads the capsule's axis by at most max_lead: a capsule the lumen holds
        # back cannot wind up an ever larger turn.
        h = lead_at_most(h, forward_axis, np.radians(c.max_lead_deg))
        travel, free = h, np.nan
        if c.assist and self._lumen_visible.HasValue(context) \
                and float(self._lumen_visible.Eval(context)[0]) > 0.5:
            ray = np.asarray(self._lumen_ray.Eval(context), dtype=float)
            if np.all(np.isfinite(ray)) and np.linalg.norm(ray) > 0.5:
                travel = R_WC @ (ray / np.linalg.norm(ray))
                if self._lumen_range.HasValue(context):
                    free = float(self._lumen_range.Eval(context)[0])
        if c.mode == "lead":
            # The EPM stays over the capsule, ahead of it along the heading by the lead.
            x[26] = np.clip(x[26] + step, -c.max_lead_distance, c.max_lead_distance)
            if np.isfinite(free) and x[26] > 0.0:
                # Over the point the lead along the lumen ray, short of the tissue there.
                xy = p_WM[:2] + min(x[26], max(0.0, free - c.assist_margin)) * travel[:2]
            else:
                xy = p_WM[:2] + x[26] * horizontal(travel)[:2]
        else:
            xy = x[10:12] + step * horizontal(travel)[:2]
        if c.max_speed > 0.0:
            move = xy - x[10:12]
            reach = c.max_speed * c.period
            if np.linalg.norm(move) > reach:
                xy = x[10:12] + move * (reach / np.linalg.norm(move))
        h = limit_pitch(h, np.radians(c.max_pitch_deg))
        x[16:19] = h
        x[10:16] = self.command_for(xy, h, p_WM, x[19])
        discrete_state.set_value(self._state, x)
