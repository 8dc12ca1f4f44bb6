"""Does the capsule fit where a scenario starts it, and does it rest there? One line saying
why not.

`start_pose` (capsule/model.py) puts the capsule's centre on the centreline at arc length
`capsule.start_s`, its axis along the tangent there. `check_start` refuses a start where
- the capsule would stick out of an end of the colon: its tips must lie within the
  centreline's [0, L], and a capsule radius inside an open end (a cut tube, an imported
  segment: there is no wall beyond it, the ragged cut of a scan least of all);
- the capsule would start inside the wall: points on its surface (its cylinder and domes,
  every 1 mm along and 24 around) lie more than `WALL_TOLERANCE` beyond the lumen's wall
  (`TubeColon.excursion`: the procedural colon's analytic wall, an imported colon's
  tabulated one), e.g. in a lumen narrower than the capsule, or in a tight bend (the
  capsule is straight).
An end is open if a ray along the line outward, from a lumen radius inside its end, meets
no wall within two lumen radii past the end (the procedural colon's ends are closed caps).

A capsule on the centreline floats in the middle of the lumen: it is not at rest. In the
procedural patient the Default EPM, above skin 12 cm over the capsule's start, is 23 cm
from it and pulls 1.3 times its weight: the capsule lifts onto the wall at 0.5-0.7 m/s.
Over an imported segment the EPM comes as close as its clearance from a flat skin 2 cm
over the mesh allows: 11 cm from the axis of a 4 cm tube, pulling 21 times the capsule's
weight, which throws it onto the wall at 2.2 m/s, past the run guard's 2 m/s
(io/guard.py). Where the lumen slopes, the capsule may instead slide, or be pulled, along
it and out of an open end. So the capsule is started where it rests: `pick_start` is
given the runner's settling (a start's physics alone at a fine step, as `capsule.settle`
does), and `rest_problem` says whether what the settling leaves is a capsule at rest
inside the colon. If the start asked for is not, the candidates of `start_candidates`
(the lumen's level places and its closed ends, then starts spread along it, nearest
first) are let settle in turn; if the capsule rests at none, one line says what happened
at each.
"""

import numpy as np

from .centerline_extraction import MeshSections

WALL_TOLERANCE = 0.0005
"""How far [m] the capsule's surface may start beyond the wall (its contact is compliant,
and a tabulated wall is a polygon's approximation)."""

REST_SETTLE = 1.0
"""Seconds a start is let settle to see where the capsule rests: the snap onto the wall
takes 0.01-0.2 s; a capsule that slides gathers speed or reaches an end within it (on the
tubes of tests/tube_set.py, those that slid out of an open end left within 0.1-0.5 s)."""
REST_SPEED = 0.05
"""Faster than this [m/s] when the settling ends, the capsule is still moving, not at rest
(the settled capsules of tests/tube_set.py's tubes: 0.000-0.011 m/s)."""
REST_WALL_TOLERANCE = 0.002
"""How far [m] a settled capsule's surface may lie beyond the wall or past an open end: the
contact lets a pressed capsule 0.3-0.6 mm into the wall; 2 mm is a capsule going into it,
or hanging out of the open end."""
CLOSED_END_TOLERANCE = 0.005
"""How far [m] a settled capsule's surface may lie past a closed end: a capsule resting
against a cap, tilted in its corner, counts up to 2.4 mm past it (measured on a flat cap,
whose extracted end tangent is a few degrees off the cap's normal), while the mesh says it
is inside by its contact's 0.5 mm; the run guard stops a capsule 5 mm past an end."""
LEVEL_SLOPE = 0.2
"""Steepest slope (sine of the capsule axis's angle to the horizontal) of a level place
(`start_candidates`): on a steeper one the default contact friction (0.2: a friction angle
of 11.3 degrees, sine 0.196) does not hold the capsule's weight."""
STANDING = np.sin(np.radians(60.0))
"""A lumen nowhere within 60 degrees of horizontal stands on end (the message says why)."""
CANDIDATE_SPACING = 0.02
"""Candidate starts closer than this [m] to one already listed are left out."""
MAX_TRIES = 6
"""Most starts `pick_start` lets settle (the one asked for included): each settling builds
the scenario's physics and simulates REST_SETTLE s (1-8 s on the tubes of
tests/tube_set.py)."""


def _open_ends(colon) -> tuple[bool, bool]:
    """Whether each end of the centreline (s = 0, s = L) is open."""
    geometry = getattr(colon, "geometry", None)
    if geometry is None:  # the procedural colon: closed at both ends
        return False, False
    sections = MeshSections(geometry)
    cl = colon.centerline
    out = []
    for s, sign in ((0.0, -1.0), (cl.length, 1.0)):
        # From a lumen radius inside (a closed end's line ends on its cap), outward.
        radius = float(np.max(colon.wall_radius(s, np.linspace(0, 2 * np.pi, 16))))
        inside = float(np.clip(s - sign * radius, 0.0, cl.length))
        start = cl.point_at(inside)
        hit = sections.ray(start, sign * cl.tangent_at(s), reach=abs(s - inside) + 2.0 * radius)
        out.append(not np.isfinite(hit))
    return out[0], out[1]


def _surface_points(centre, axis, radius, length, step=0.001, around=24):
    """Points on a capsule's surface: its overall `length` (tip to tip) along `axis`."""
    half = 0.5 * length
    cylinder = max(0.0, half - radius)
    x = np.linspace(-half, half, max(3, int(np.ceil(length / step)) + 1))
    rho = np.where(np.abs(x) <= cylinder, radius,
                   np.sqrt(np.maximum(radius ** 2 - (np.abs(x) - cylinder) ** 2, 0.0)))
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    ring = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v
    points = centre + x[:, None, None] * axis + rho[:, None, None] * ring[None, :, :]
    return points.reshape(-1, 3), np.repeat(x, around)


def _end_name(open_end: bool) -> str:
    return "open end" if open_end else "closed end"


def _listed(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _start_bounds(colon, capsule_radius, capsule_length, ends) -> tuple[float, float]:
    """The lowest and highest start at which the capsule's tips lie within the centreline,
    and a capsule radius inside an open end."""
    half = 0.5 * capsule_length
    low = half + (capsule_radius if ends[0] else 0.0)
    high = colon.centerline.length - half - (capsule_radius if ends[1] else 0.0)
    return low, high


def _check_start(colon, start_s, capsule_radius, capsule_length, ends) -> None:
    cl = colon.centerline
    low, high = _start_bounds(colon, capsule_radius, capsule_length, ends)
    if start_s < low:
        raise ValueError(f"capsule.start_s {start_s:g} m: the capsule would stick out of the "
                         f"colon's {_end_name(ends[0])} at s = 0 (needs >= {low:.3f} m)")
    if start_s > high:
        raise ValueError(f"capsule.start_s {start_s:g} m: the capsule would stick out of the "
                         f"colon's {_end_name(ends[1])} at s = {cl.length:.3f} m (needs <= "
                         f"{high:.3f} m)")
    centre = cl.point_at(start_s)
    axis = cl.tangent_at(start_s)
    points, x = _surface_points(centre, axis, capsule_radius, capsule_length)
    excursion = colon.excursion(points)
    worst = int(np.argmax(excursion))
    if excursion[worst] > WALL_TOLERANCE:
        s_worst = cl.closest(points[worst])[0]
        around = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
        narrowest = float(np.min(colon.wall_radius(np.full(64, s_worst), around)))
        raise ValueError(
            f"capsule.start_s {start_s:g} m: the capsule would start "
            f"{1000 * excursion[worst]:.1f} mm inside the wall (at s = {s_worst:.3f} m the "
            f"lumen is {1000 * narrowest:.1f} mm in radius at its narrowest, the capsule "
            f"{1000 * capsule_radius:.1f} mm)")


def check_start(colon, start_s: float, capsule_radius: float, capsule_length: float) -> None:
    """Raises ValueError (one line) if a capsule of `capsule_radius` and overall
    `capsule_length` (tip to tip, m), started on the centreline at `start_s` (m) along the
    tangent, would stick out of the colon's ends or start inside its wall. `colon`: a
    `TubeColon` (procedural or imported)."""
    _check_start(colon, start_s, capsule_radius, capsule_length, _open_ends(colon))


def _axis_of(q_wxyz) -> np.ndarray:
    """The body's z axis (the capsule's) in world of a quaternion [w, x, y, z]."""
    w, x, y, z = np.asarray(q_wxyz, dtype=float) / np.linalg.norm(q_wxyz)
    return np.array([2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)])


def _rest_problem(colon, state, capsule_radius, capsule_length, ends) -> str | None:
    state = np.asarray(state, dtype=float)
    if not np.all(np.isfinite(state)):
        return "was thrown out of the colon (its state became NaN or infinite)"
    cl = colon.centerline
    p = state[4:7]
    s, _, _ = cl.closest(p)
    for s_end, sign, name, is_open in ((0.0, -1.0, "0", ends[0]),
                                       (cl.length, 1.0, f"{cl.length:.3f} m", ends[1])):
        if s == s_end:
            past = sign * float((p - cl.point_at(s_end)) @ cl.tangent_at(s_end))
            if past > 0.0:
                return f"left the colon through its {_end_name(is_open)} at s = {name}"
    points, _ = _surface_points(p, _axis_of(state[:4]), capsule_radius, capsule_length)
    excursion = colon.excursion(points)
    s_points = cl.closest(points)[0]
    for s_end, is_open in ((0.0, ends[0]), (cl.length, ends[1])):
        at_end = s_points == s_end
        past = float(np.max(excursion[at_end], initial=-np.inf))
        if past > (REST_WALL_TOLERANCE if is_open else CLOSED_END_TOLERANCE):
            return (f"sticks out {1000 * past:.1f} mm past the colon's {_end_name(is_open)} "
                    f"at s = {s_end:.3f} m")
    inside = (s_points > 0.0) & (s_points < cl.length)
    if np.any(inside) and np.max(excursion[inside]) > REST_WALL_TOLERANCE:
        worst = int(np.flatnonzero(inside)[np.argmax(excursion[inside])])
        return (f"went {1000 * excursion[worst]:.1f} mm into the wall at s = "
                f"{s_points[worst]:.3f} m")
    speed = float(np.linalg.norm(state[10:13]))
    if speed > REST_SPEED:
        return f"was still moving at {speed:.2f} m/s at s = {float(s):.3f} m"
    return None


def rest_problem(colon, state, capsule_radius: float, capsule_length: float) -> str | None:
    """Why a capsule in `state` (13: [q_WB (wxyz), p_WB, w_WB, v_WB], as the station's
    capsule.state) is not at rest inside the colon, as a clause ("left the colon through
    its open end at s = 0, 12 mm past it"), or None if it is: its state finite, its centre
    within the colon's ends, its surface (overall `capsule_length` tip to tip) no more than
    `REST_WALL_TOLERANCE` beyond the wall or past an end, and slower than `REST_SPEED`."""
    return _rest_problem(colon, state, capsule_radius, capsule_length, _open_ends(colon))


def _slope(colon, s, capsule_length) -> np.ndarray:
    """Sine of the angle to the horizontal of the chord between the capsule's tips when it
    is centred on the centreline at s."""
    cl = colon.centerline
    half = 0.5 * capsule_length
    chord = cl.point_at(s + half) - cl.point_at(s - half)
    return np.abs(chord[..., 2]) / np.maximum(np.linalg.norm(chord, axis=-1), 1e-12)


def _places(colon, capsule_radius, capsule_length, ends):
    """(level places, closed-end starts, least slope): where a capsule may rest other than
    where it was asked to start (`start_candidates`)."""
    low, high = _start_bounds(colon, capsule_radius, capsule_length, ends)
    if high <= low:
        return np.zeros(0), [], 0.0
    s = np.linspace(low, high, max(3, int(np.ceil((high - low) / 0.002)) + 1))
    slope = _slope(colon, s, capsule_length)
    padded = np.concatenate([[np.inf], slope, [np.inf]])
    level = s[(slope <= LEVEL_SLOPE) & (slope <= padded[:-2]) & (slope <= padded[2:])]
    closed = [x for x, is_open in ((low, ends[0]), (high, ends[1])) if not is_open]
    return level, closed, float(np.min(slope))


def _candidates(colon, start_s, capsule_radius, capsule_length, ends, count):
    level, closed, _ = _places(colon, capsule_radius, capsule_length, ends)
    low, high = _start_bounds(colon, capsule_radius, capsule_length, ends)
    spread = np.linspace(low, high, count) if high > low else np.zeros(0)
    chosen = [start_s]
    for group in (np.concatenate([level, closed]), spread):
        for candidate in sorted(group, key=lambda x: abs(x - start_s)):
            if len(chosen) >= count:
                return chosen
            if min(abs(candidate - c) for c in chosen) < CANDIDATE_SPACING:
                continue
            try:
                _check_start(colon, float(candidate), capsule_radius, capsule_length, ends)
            except ValueError:
                continue  # the capsule does not fit there (a narrow or tightly bent lumen)
            chosen.append(float(candidate))
    return chosen


def start_candidates(colon, start_s: float, capsule_radius: float, capsule_length: float,
                     count: int = MAX_TRIES) -> list[float]:
    """Up to `count` starts (m) to let settle, in order: `start_s`; then, nearest to it
    first, the lumen's level places (where the capsule, centred on the centreline, lies
    within `LEVEL_SLOPE` of horizontal, at a local minimum of its slope: a valley holds it
    against gravity, a crest under the EPM against its pull, as the procedural rectum's
    highest point does) and the starts at its closed ends (the capsule's tip on the cap,
    where it may rest against it); then, nearest first, `count` starts spread evenly along
    the colon (where the EPM's pull, pressing the capsule onto the wall, may hold it on a
    steeper slope). Each at least `CANDIDATE_SPACING` from those before it, and where
    `check_start` accepts the capsule."""
    return _candidates(colon, start_s, capsule_radius, capsule_length, _open_ends(colon),
                       count)


def pick_start(colon, start_s: float, capsule_radius: float, capsule_length: float, settle,
               tries: int = MAX_TRIES) -> tuple[float, str | None]:
    """Where the run starts the capsule so that it rests: (start, note).

    `settle(s)` returns the capsule's state (13, as `rest_problem` takes) after the
    capsule, started on the centreline at s with the EPM where the run starts it for that
    start, was let settle (`REST_SETTLE` s of the scenario's physics alone). The start is
    `start_s` (note None) if the capsule rests there; otherwise the first of
    `start_candidates` where it does, with a one-line note saying why `start_s` was not
    used.

    Raises:
        ValueError (one line): `check_start` refuses `start_s`, or the capsule rests at
            none of the candidates (what happened at each).
    """
    ends = _open_ends(colon)
    _check_start(colon, start_s, capsule_radius, capsule_length, ends)
    candidates = _candidates(colon, start_s, capsule_radius, capsule_length, ends, tries)
    tried = []
    for s in candidates:
        try:
            state = settle(s)
        except (RuntimeError, ValueError, ArithmeticError) as e:
            # The settling's simulation failed: a capsule thrown out of the colon and into
            # the EPM ends with a state numpy and Drake cannot take (a NaN inertia).
            text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            tried.append((s, f"was thrown out of the colon (its settling failed: {text})"))
            continue
        problem = _rest_problem(colon, state, capsule_radius, capsule_length, ends)
        if problem is None:
            if s == start_s:
                return s, None
            return s, (f"capsule.start_s {start_s:g} m: let settle there, the capsule "
                       f"{tried[0][1]}; it starts at s = {s:.3f} m instead, where it rests")
        tried.append((s, problem))
    starts = {}  # the same thing at several starts is said once
    for s, problem in tried:
        starts.setdefault(problem, []).append(f"{s:.3f}")
    what = "; ".join(f"at s = {_listed(names)} m it {problem}"
                     for problem, names in starts.items())
    level, closed, least = _places(colon, capsule_radius, capsule_length, ends)
    if len(level) == 0 and not closed:
        what += (f" (the lumen has no level place, within "
                 f"{np.degrees(np.arcsin(LEVEL_SLOPE)):.1f} degrees of horizontal, where "
                 f"friction may hold the capsule's weight: it slopes by "
                 f"{np.degrees(np.arcsin(min(1.0, least))):.0f} degrees or more everywhere; "
                 f"both its ends are open"
                 + ("; z is up and the import keeps the mesh's axes, so a mesh made along "
                    "its z axis stands on end" if least > STANDING else "") + ")")
    raise ValueError(f"capsule.start_s {start_s:g} m: the capsule rests at none of the "
                     f"{len(tried)} starts let settle in this colon: {what}")
