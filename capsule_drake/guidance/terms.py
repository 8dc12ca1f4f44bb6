"""The pseudo-force on the operator's hand: where the lumen is, how near the wall, which way on.

The haptic stylus (Phantom Omni / Geomagic Touch class: 3.3 N peak, 1 kHz servo loop;
docs/sources.md section 4) pushes the operator's hand with the weighted sum of three terms:

(a) lumen attraction, from the lumen direction seen by the camera (unit ray r_C in the camera
    frame C: x right, y down, z forward along the optical axis):
        F_C = confidence * [k_lateral r_x, k_lateral r_y, k_forward max(r_z, 0)],
    so the lateral part has magnitude k_lateral sin(offset angle) and points toward the lumen
    in the image, and a centred lumen pulls straight ahead; zero when the lumen is not seen;
(b) wall avoidance, a spring-damper on the capsule's distance d to the mucosa, along the
    wall's inward normal n (toward the centreline):
        F = max(k_wall (d0 - d) - c_wall d_dot, 0) n     while d < d0, else 0;
(c) a potential field along the colon, U(p) = k_along (L - s(p)) + k_radial rho(p)^2 / 2
    with s the centreline arc length of the capsule centre (0 at the anus, L at the cecum)
    and rho its distance from the centreline: F = -grad U. The exact gradient is used,
    grad s = t / (1 - (p - c(s)) . c''(s)): off the centreline of a bend the arc length runs
    faster on the inside than on the outside, so the pull along t is not k_along there
    (k_along t - k_radial rho e_rho is only its limit at rho -> 0).

World-frame terms go world -> camera (capsule pose, camera pose in the capsule body) ->
haptic device frame D (Phantom convention: x right, y up, z toward the operator). With the
operator facing the camera image, R_DC = diag(1, -1, -1): pushing the stylus away from the
operator (-z_D) is camera forward. The sum is saturated to the device's force limit by
scaling its norm (direction kept).

Inputs that are not finite carry no information: the term that needs them is zero, and the
result says so (`PseudoForce.invalid`), so a caller can count them.
"""

import dataclasses

import math

import numpy as np

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.schema import need_range

WALL_SAMPLES = 5
"""Points on the capsule's axis segment at which the wall distance is evaluated."""

TERMS = ("lumen", "wall", "potential")
"""The terms, in the order of `PseudoForce.terms_D` and `PseudoForce.invalid`."""

# The denominator of grad s, 1 - (p - c) . c'', reaches 0 on the evolute of a bend (the
# centre of curvature), where s(p) stops being differentiable; floor it there.
_MIN_ARC_RATE = 0.1


@dataclasses.dataclass
class PseudoForceConfig:
    """Gains and limits of the pseudo-force on the haptic stylus; YAML-loadable, all default.

    Each default gain makes its term alone 1-2 N in its typical situation: felt clearly,
    about the device's continuous force (0.88 N) and below its 3.3 N peak (docs/sources.md
    section 4), so two terms can add before the saturation bends the sum. U throughout.
    """

    # Weight of the lumen attraction (a) in the sum (dimensionless).
    lumen_weight: float = 1.0
    # Weight of the wall avoidance (b) in the sum (dimensionless).
    wall_weight: float = 1.0
    # Weight of the potential field (c): off by default, since it reads the true centreline
    # (a guidance aid of a simulator, not of a real procedure).
    potential_weight: float = 0.0
    # Lateral gain (N): the lateral force is k_lateral sin(offset angle): 1.4 N for a lumen
    # 45 deg off the image centre, 2 N at 90 deg (the edge of a 172-deg fisheye).
    k_lateral: float = 2.0
    # Forward gain (N): the pull straight ahead when the lumen is centred, about the
    # device's continuous force, so it can be held for as long as the lumen stays ahead.
    k_forward: float = 1.0
    # Wall stiffness (N/m of capsule travel): 1.6 N when the capsule touches the wall
    # (d = 0, d0 = 4 mm). What the hand feels is k_wall over the teleoperation scale (stylus
    # metres per capsule metre): at 1:1, 400 N/m, the Touch's stiffness limit (the Omni's is
    # 700 N/m), so a wall rendered at scales >= 1 stays within what both devices hold stably.
    k_wall: float = 400.0
    # Wall damping (N s/m) on the approach speed along the wall normal: +0.5 N at 1 cm/s, a
    # magnetically driven capsule's typical speed, a third of the spring's push at contact.
    c_wall: float = 50.0
    # Distance to the wall (m) below which the wall term acts (d0): two thirds of the
    # capsule's radius. A centred capsule is 8.7 mm from the wall of the narrowest segment
    # (14.5 mm radius), so the middle of the lumen stays free of it.
    wall_distance: float = 0.004
    # Pull along the colon toward the cecum (N), on the centreline.
    k_along: float = 1.0
    # Pull back to the centreline (N/m): 1 N at 1 cm off it, 2.9 N at the wall of the widest
    # segment (35 mm radius minus the capsule's 5.8 mm).
    k_radial: float = 100.0
    # Saturation of the total force's norm (N): the device's peak force.
    force_limit: float = 3.3
    # Device frame D in the camera frame C, roll-pitch-yaw (deg) of R_DC. [180, 0, 0] is
    # diag(1, -1, -1): image right = stylus right, image down = stylus down, camera forward
    # = stylus away from the operator.
    device_from_camera_rpy_deg: list[float] = dataclasses.field(
        default_factory=lambda: [180.0, 0.0, 0.0])
    # Sample-and-hold period (s) of the force. A sample costs ~1.5 ms of Python (the wall
    # query), so the device's 1 kHz servo rate would cost ~1.5 s per simulated second; at
    # 100 Hz it is faster than the camera's 4-35 frames per second and the device's servo
    # loop holds it between samples.
    update_period: float = 0.01


def check_pseudo_force_config(config: PseudoForceConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    for name, unit in (("lumen_weight", ""), ("wall_weight", ""), ("potential_weight", ""),
                       ("k_lateral", "N"), ("k_forward", "N"), ("k_wall", "N/m"),
                       ("c_wall", "N s/m"), ("k_along", "N"), ("k_radial", "N/m")):
        need_range(getattr(config, name), f"pseudo_force.{name}", ">= 0", unit)
    need_range(config.wall_distance, "pseudo_force.wall_distance", "(0, 0.05]", "m",
               "the widest lumen's radius")
    need_range(config.force_limit, "pseudo_force.force_limit", "> 0", "N")
    need_range(config.update_period, "pseudo_force.update_period", ">= 0.0001", "s",
               "a sample costs ~1.5 ms of computation")
    rpy = config.device_from_camera_rpy_deg
    if len(rpy) != 3:
        raise ValueError(f"pseudo_force.device_from_camera_rpy_deg must be three angles "
                         f"(roll, pitch, yaw), got {rpy!r}")
    need_range(list(rpy), "pseudo_force.device_from_camera_rpy_deg", "[-360, 360]", "deg")


def rotation_from_rpy_deg(rpy_deg) -> np.ndarray:
    """Rotation matrix of roll-pitch-yaw angles (deg), Drake's convention R = Rz Ry Rx."""
    roll, pitch, yaw = np.deg2rad(np.asarray(rpy_deg, dtype=float))
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    R_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    R_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    R_z = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return R_z @ R_y @ R_x


def saturate(force, limit: float) -> np.ndarray:
    """The force with its norm clipped to `limit` (N), direction kept."""
    force = np.asarray(force, dtype=float)
    norm = np.linalg.norm(force)
    return force * (limit / norm) if norm > limit else force.copy()


def saturate_checked(force, limit: float) -> tuple[np.ndarray, bool, bool]:
    """A force for a device: (force (3,), saturated, invalid). A force with any NaN or inf
    component is replaced by zero as a whole (invalid = True): zeroing only the bad component
    would push the hand in a direction nobody commanded. A force longer than `limit` is
    scaled down to it, keeping its direction (saturated = True)."""
    f = np.asarray(force, dtype=float).reshape(3)
    norm = math.sqrt(f @ f)
    if not math.isfinite(norm):
        if not np.all(np.isfinite(f)):
            return np.zeros(3), False, True
        norm = float(np.linalg.norm(f))  # finite, but its square overflowed
    if norm > limit:
        return f * (limit / norm), True, False
    return f.copy(), False, False


def lumen_attraction(ray_C, visible: bool, confidence: float, k_lateral: float,
                     k_forward: float) -> np.ndarray:
    """Term (a) in the camera frame (N): toward the lumen in the image, forward when centred.

    Args:
        ray_C: direction of the lumen centre in C (normalised here; must be nonzero).
        visible: whether the lumen is seen; if not, the force is zero.
        confidence: the detector's confidence, clipped to [0, 1]; scales the force.
    """
    if not visible:
        return np.zeros(3)
    r = np.asarray(ray_C, dtype=float)
    r = r / np.linalg.norm(r)
    scale = float(np.clip(confidence, 0.0, 1.0))
    return scale * np.array([k_lateral * r[0], k_lateral * r[1], k_forward * max(r[2], 0.0)])


def capsule_axis_points(R_WB, p_WB, length: float,
                        samples: int = WALL_SAMPLES) -> np.ndarray:
    """(samples, 3) world points evenly spaced on the capsule's axis segment, body z from
    -length/2 to +length/2."""
    z_B = np.linspace(-0.5 * length, 0.5 * length, samples)
    return np.asarray(p_WB, dtype=float) + z_B[:, None] * np.asarray(R_WB, dtype=float)[:, 2]


def toward_centerline(centerline, p_W) -> tuple[np.ndarray, float, float]:
    """Unit vector from p_W toward the centreline in the normal plane at its closest station.

    Returns (e_W (3,), rho [m], s [m]); e_W is zero on the centreline itself.
    """
    s, _, _ = centerline.closest(np.asarray(p_W, dtype=float))
    offset = np.asarray(p_W, dtype=float) - centerline.point_at(s)
    t = centerline.tangent_at(s)
    radial = offset - np.dot(offset, t) * t
    rho = float(np.linalg.norm(radial))
    e = -radial / rho if rho > 1e-12 else np.zeros(3)
    return e, rho, float(s)


@dataclasses.dataclass(frozen=True)
class WallClearance:
    """The capsule's nearest approach to the wall.

    Attributes:
        distance: d, from the capsule's surface to the mucosa along the wall normal [m]
            (< 0: pressed into the tissue).
        normal_W: unit inward normal at the critical point (toward the centreline).
        rate: d_dot [m/s], the critical point's velocity along normal_W.
        point_W: the critical point on the capsule's axis [m].
    """

    distance: float
    normal_W: np.ndarray
    rate: float
    point_W: np.ndarray


def wall_clearance(colon, R_WB, p_WB, w_WB, v_WB, radius: float,
                   length: float,
                   samples: int = WALL_SAMPLES) -> WallClearance:
    """Distance from the capsule (a capsule shape along body z) to the colon wall.

    Each axis sample's surface distance is -colon.excursion(point) - radius; the smallest one
    is the critical point. Its velocity v + w x r along the inward normal is the rate.
    """
    points = capsule_axis_points(R_WB, p_WB, length, samples)
    distances = -colon.excursion(points) - radius
    k = int(np.argmin(distances))
    normal, _, _ = toward_centerline(colon.centerline, points[k])
    velocity = np.asarray(v_WB, dtype=float) + np.cross(w_WB, points[k] - np.asarray(p_WB))
    return WallClearance(float(distances[k]), normal, float(velocity @ normal), points[k])


def wall_avoidance(distance: float, rate: float, normal_W, k_wall: float, c_wall: float,
                   wall_distance: float) -> np.ndarray:
    """Term (b) in the world frame (N): a spring-damper pushing along the inward normal while
    the capsule is nearer the wall than `wall_distance` (d0); never pulls toward the wall."""
    if distance >= wall_distance:
        return np.zeros(3)
    magnitude = max(k_wall * (wall_distance - distance) - c_wall * rate, 0.0)
    return magnitude * np.asarray(normal_W, dtype=float)


def colon_potential(centerline, p_W, k_along: float, k_radial: float) -> np.ndarray:
    """U(p) = k_along (L - s(p)) + k_radial rho(p)^2 / 2 [J] at (K, 3) or (3,) points."""
    s, rho, _ = centerline.closest(np.asarray(p_W, dtype=float))
    return k_along * (centerline.length - s) + 0.5 * k_radial * np.square(rho)


def colon_potential_force(centerline, p_W, k_along: float, k_radial: float) -> np.ndarray:
    """Term (c) in the world frame (N): -grad U at one point p_W.

    grad rho is the unit radial vector; grad s = t / (1 - (p - c(s)) . c''(s)) (from
    differentiating the foot-point condition (p - c(s)) . t(s) = 0), with c'' = dt/ds by a
    central difference of the spline's tangent. Past either end of the centreline s is
    clamped, so it has no gradient there.
    """
    p = np.asarray(p_W, dtype=float)
    e, rho, s = toward_centerline(centerline, p)
    length = centerline.length
    t = centerline.tangent_at(s)
    offset = p - centerline.point_at(s)
    along = np.zeros(3)
    if 0.0 < s < length:
        s_minus, s_plus = max(s - 1e-4, 0.0), min(s + 1e-4, length)
        curvature_W = ((centerline.tangent_at(s_plus) - centerline.tangent_at(s_minus))
                       / (s_plus - s_minus))
        along = t / max(1.0 - float(offset @ curvature_W), _MIN_ARC_RATE)
    # e points toward the centreline, i.e. along -grad rho.
    return k_along * along + k_radial * rho * e


@dataclasses.dataclass(frozen=True)
class PseudoForce:
    """One sample of the pseudo-force.

    Attributes:
        F_D: the saturated total in the device frame (N).
        terms_D: (3, 3) rows lumen, wall, potential: each term weighted, in the device frame,
            before saturation (N).
        wall_distance: d [m]; NaN when the capsule pose is not finite.
        invalid: (3,) bool per term (lumen, wall, potential): its inputs were not finite,
            so the term is zero (flagged whatever the term's weight).
    """

    F_D: np.ndarray
    terms_D: np.ndarray
    wall_distance: float
    invalid: np.ndarray


def pseudo_force(colon, config: PseudoForceConfig, R_BC, ray_C, lumen_visible: float,
                 lumen_confidence: float, capsule_state, radius: float,
                 length: float) -> PseudoForce:
    """The pseudo-force of all three terms, from the inputs of `PseudoForceField`.

    Args:
        colon: the Colon (wall and centreline).
        config: gains (`check_pseudo_force_config` is not called here).
        R_BC: (3, 3) camera orientation in the capsule body.
        ray_C: lumen direction in C; lumen_visible: > 0.5 means seen; lumen_confidence in
            [0, 1].
        capsule_state: (13,) [q_WB (w, x, y, z), p_WB, w_WB, v_WB].
        radius, length: the capsule's collision shape (m).
    """
    c = config
    invalid = np.zeros(3, dtype=bool)
    terms_C = np.zeros((3, 3))

    visible_value = float(lumen_visible)
    ray = np.asarray(ray_C, dtype=float)
    if not np.isfinite(visible_value):
        invalid[0] = True
    elif visible_value > 0.5:
        if (np.all(np.isfinite(ray)) and np.linalg.norm(ray) > 0.0
                and np.isfinite(lumen_confidence)):
            terms_C[0] = c.lumen_weight * lumen_attraction(
                ray, True, lumen_confidence, c.k_lateral, c.k_forward)
        else:
            invalid[0] = True

    state = np.asarray(capsule_state, dtype=float)
    q, p_WB, w_WB, v_WB = state[:4], state[4:7], state[7:10], state[10:13]
    pose_ok = bool(np.all(np.isfinite(state[:7])) and np.linalg.norm(q) > 0.0)
    wall_distance = np.nan
    if pose_ok:
        R_WB = rotation_from_quaternion(q)
        R_CW = (R_WB @ np.asarray(R_BC, dtype=float)).T
        if c.wall_weight > 0.0:  # (the wall model is ~1 ms a sample: only when used)
            clearance = wall_clearance(colon, R_WB, p_WB, np.nan_to_num(w_WB),
                                       np.nan_to_num(v_WB), radius, length)
            wall_distance = clearance.distance
        if not np.all(np.isfinite(state[7:13])):
            invalid[1] = True
        elif c.wall_weight > 0.0:
            F_W = wall_avoidance(clearance.distance, clearance.rate, clearance.normal_W,
                                 c.k_wall, c.c_wall, c.wall_distance)
            terms_C[1] = c.wall_weight * (R_CW @ F_W)
        if c.potential_weight > 0.0:
            F_W = colon_potential_force(colon.centerline, p_WB, c.k_along, c.k_radial)
            terms_C[2] = c.potential_weight * (R_CW @ F_W)
    else:
        invalid[1:] = True

    R_DC = rotation_from_rpy_deg(c.device_from_camera_rpy_deg)
    terms_D = terms_C @ R_DC.T
    F_D = saturate(terms_D.sum(axis=0), c.force_limit)
    return PseudoForce(F_D, terms_D, float(wall_distance), invalid)
