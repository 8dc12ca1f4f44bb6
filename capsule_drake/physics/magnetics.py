"""Point-dipole magnetics: field, energy, force and torque between two magnets.

Every function takes world-frame vectors and returns world-frame vectors. ``p`` is
always the offset *from the source dipole to the target dipole*,
``p = r_target - r_source``, in metres; moments are in A m^2, fields in tesla,
forces in newtons, torques in newton metres.

The equations are the point-dipole model of Mahoney & Abbott, "Generating rotating
magnetic fields with a single permanent magnet for propulsion of untethered magnetic
devices in a lumen", IEEE T-RO 2014, and "Five-degree-of-freedom manipulation of an
untethered magnetic device in fluid using a single permanent magnet with application
in stomach capsule endoscopy", IJRR 2016 (eqs. 1-3); see also Furlani,
"Permanent Magnet and Electromechanical Devices", Academic Press 2001, ch. 2.

With ``r = |p|`` and ``u = p / r``:

    B(p)  = mu0 / (4 pi r^3) (3 u u^T - I) m_s
    U     = -m_t . B
    F     = 3 mu0 / (4 pi r^4) [m_s (m_t.u) + m_t (m_s.u) + u (m_s.m_t - 5 (m_s.u)(m_t.u))]
    T     = m_t x B = mu0 / (4 pi r^3) m_t x ((3 u u^T - I) m_s)

The seed paper (the 2017 simulation-environment paper) prints ``|p_hat|^3`` (always 1) in the
torque's denominator; the correct denominator is ``|p|^3``, as written above.

All generic functions are written with ``@``, ``*``, ``**`` and explicit components
only, so they run unchanged when the arrays hold ``pydrake.autodiffutils.AutoDiffXd``
(``dtype=object``): this is what lets a Drake diagram containing them be linearised.
``dipole_pair_interaction_float`` is a separate float-only fast path (plain Python
floats, no numpy temporaries) for the simulator's 1 kHz loop; the tests check that it
agrees with the generic path.
"""

import dataclasses
import functools
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from capsule_drake.schema import need_range

# Vacuum permeability. The exact pre-2019 value; the SI 2019 CODATA value
# (1.25663706212e-6 N/A^2) differs from it by ~5e-10 relative, far below anything
# the point-dipole model can resolve.
MU0 = 4e-7 * math.pi

# Below this centre distance the interaction is frozen at this distance (see
# ``_guarded_offset``). 1 mm: far smaller than any real magnet pair can get (their
# bodies would overlap), large enough that 1/r^4 stays finite in double precision.
DEFAULT_MIN_DISTANCE = 1e-3

_K = MU0 / (4.0 * math.pi)  # = 1e-7 T m / A


def _cross(a, b):
    """a x b, written out so that it also works on object (AutoDiffXd) arrays (and costs
    a few us on floats, where np.cross costs ~20 us)."""
    return np.array(
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    )


def _guarded_offset(p, min_distance):
    """Returns ``(p_eff, r_eff)`` for the offset ``p``, or ``None`` when ``p == 0``.

    The point-dipole interaction is singular at r = 0 (B ~ 1/r^3, F ~ 1/r^4).
    Physical magnets cannot overlap, so any centre distance below a few millimetres
    means the simulation has already gone wrong (e.g. a stiff contact was
    penetrated); rather than emitting inf/NaN that would poison the integrator, the
    interaction is evaluated at ``min_distance`` along the same direction. Exactly at
    ``p = 0`` there is no direction, and the callers return zeros.
    """
    r2 = p @ p
    if r2 == 0.0:
        return None
    r = r2**0.5
    if r < min_distance:
        return p * (min_distance / r), min_distance
    return p, r


def dipole_field(m_source, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Magnetic flux density (T) of the dipole ``m_source`` at offset ``p``.

    Args:
        m_source: source moment (A m^2), world frame, shape (3,).
        p: offset from the source to the field point (m), world frame.
        min_distance: guard radius (m); inside it the field is evaluated at
            ``min_distance`` along ``p`` and is zero at ``p = 0``
            (see module docstring and ``_guarded_offset``).
    """
    m_source = np.asarray(m_source)
    p = np.asarray(p)
    guarded = _guarded_offset(p, min_distance)
    if guarded is None:
        return m_source * 0.0
    p, r = guarded
    u = p / r
    return (_K / r**3) * (u * (3.0 * (u @ m_source)) - m_source)


def dipole_energy(m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Interaction energy (J) ``U = -m_target . B_source(p)``."""
    return -(np.asarray(m_target) @ dipole_field(m_source, p, min_distance))


def dipole_force(m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Force (N) on ``m_target`` at offset ``p`` from ``m_source``.

    Closed form of ``grad_p (m_target . B_source(p))`` (Mahoney & Abbott, IJRR
    2016, eq. 3). Inside ``min_distance`` the force is that at ``min_distance``
    along the same direction (it is then no longer the gradient of the energy).
    """
    m_source = np.asarray(m_source)
    m_target = np.asarray(m_target)
    p = np.asarray(p)
    guarded = _guarded_offset(p, min_distance)
    if guarded is None:
        return p * 0.0
    p, r = guarded
    u = p / r
    ms_u = m_source @ u
    mt_u = m_target @ u
    ms_mt = m_source @ m_target
    return (3.0 * _K / r**4) * (
        m_source * mt_u + m_target * ms_u + u * (ms_mt - 5.0 * ms_u * mt_u)
    )


def dipole_torque(m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Torque (N m) on ``m_target`` about its own centre: ``m_target x B_source(p)``.

    Scales as 1/|p|^3 (the seed paper's ``|p_hat|^3`` is a typo).
    """
    return _cross(np.asarray(m_target), dipole_field(m_source, p, min_distance))


class DipolePairWrench(NamedTuple):
    """Wrench on each magnet of a pair, each torque taken about that magnet's centre."""

    force_target: np.ndarray
    torque_target: np.ndarray
    force_source: np.ndarray
    torque_source: np.ndarray


def dipole_pair_wrench(m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Force and torque on both magnets of a pair.

    The target gets ``(F, T)`` from ``dipole_force``/``dipole_torque``; the source
    gets the reaction ``-F`` and, about its own centre, ``-T - p x F``. The lever
    arm uses the true ``p`` even inside the ``min_distance`` guard, so total
    force and total torque about any point are exactly zero in every case.

    Returns:
        DipolePairWrench(force_target, torque_target, force_source, torque_source).
    """
    p = np.asarray(p)
    force = dipole_force(m_source, m_target, p, min_distance)
    torque = dipole_torque(m_source, m_target, p, min_distance)
    return DipolePairWrench(force, torque, -force, -torque - _cross(p, force))


class DipolePairInteraction(NamedTuple):
    """Everything a pair of dipoles does to each other (world frame).

    Torques are about each magnet's own centre. ``field_at_target`` is the source's
    field at the target, ``field_at_source`` the target's field at the source.
    """

    field_at_target: np.ndarray
    field_at_source: np.ndarray
    force_target: np.ndarray
    torque_target: np.ndarray
    force_source: np.ndarray
    torque_source: np.ndarray


def dipole_pair_interaction(m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE):
    """Fields at, and wrenches on, both magnets of a pair (generic scalar type)."""
    p = np.asarray(p)
    field_at_target = dipole_field(m_source, p, min_distance)
    field_at_source = dipole_field(m_target, -p, min_distance)
    force = dipole_force(m_source, m_target, p, min_distance)
    torque = _cross(np.asarray(m_target), field_at_target)
    return DipolePairInteraction(
        field_at_target,
        field_at_source,
        force,
        torque,
        -force,
        -torque - _cross(p, force),
    )


@njit(cache=True)
def dipole_pair_interaction_float(
    m_source, m_target, p, min_distance=DEFAULT_MIN_DISTANCE
):
    """Float-only fast path of ``dipole_pair_interaction`` (same result).

    Works on plain Python floats component by component: for 3-vectors this is
    several times faster than numpy, whose per-call overhead dominates at this size.
    Accepts 3-tuples of floats (or 3-arrays) and returns a ``DipolePairInteraction`` of
    3-tuples of floats (no numpy arrays are made: ``MagneticForce`` calls this at every
    step of a 1 kHz simulation and hands the tuples straight to Drake). Compiled with
    Numba: the implicit torque's stiffness (physics/implicit_torque.py) calls it from
    machine code; from Python a call costs what the plain-float version did (~3 us).
    """
    sx, sy, sz = m_source
    tx, ty, tz = m_target
    px, py, pz = p
    r2 = px * px + py * py + pz * pz
    if r2 == 0.0:
        zero = (0.0, 0.0, 0.0)
        return DipolePairInteraction(zero, zero, zero, zero, zero, zero)
    r = math.sqrt(r2)
    r_eff = min_distance if r < min_distance else r
    ux, uy, uz = px / r, py / r, pz / r
    k3 = _K / (r_eff * r_eff * r_eff)
    s_u = sx * ux + sy * uy + sz * uz
    t_u = tx * ux + ty * uy + tz * uz
    s_t = sx * tx + sy * ty + sz * tz
    # Field of the source at the target, and of the target at the source
    # (u -> -u leaves 3 u u^T unchanged).
    a, c = 3.0 * s_u, 3.0 * t_u
    bx, by, bz = k3 * (a * ux - sx), k3 * (a * uy - sy), k3 * (a * uz - sz)
    k4 = 3.0 * k3 / r_eff
    w = s_t - 5.0 * s_u * t_u
    fx = k4 * (sx * t_u + tx * s_u + ux * w)
    fy = k4 * (sy * t_u + ty * s_u + uy * w)
    fz = k4 * (sz * t_u + tz * s_u + uz * w)
    # Torque on the target about its centre: m_t x B.
    qx, qy, qz = ty * bz - tz * by, tz * bx - tx * bz, tx * by - ty * bx
    # Reaction torque on the source about its centre: -T - p x F.
    return DipolePairInteraction(
        (bx, by, bz),
        (k3 * (c * ux - tx), k3 * (c * uy - ty), k3 * (c * uz - tz)),
        (fx, fy, fz),
        (qx, qy, qz),
        (-fx, -fy, -fz),
        (
            -qx - (py * fz - pz * fy),
            -qy - (pz * fx - px * fz),
            -qz - (px * fy - py * fx),
        ),
    )


# --- Moments from geometry -------------------------------------------------------
# A uniformly magnetised body of volume V and remanence Br (T) has m = Br V / mu0
# (Furlani 2001, sec. 2.7; exact for the far field of any shape).


def cylinder_moment(diameter, length, remanence):
    """Moment (A m^2) of an axially magnetised cylinder: Br pi (D/2)^2 L / mu0."""
    return remanence * math.pi * (0.5 * diameter) ** 2 * length / MU0


def sphere_moment(diameter, remanence):
    """Moment (A m^2) of a uniformly magnetised sphere: Br pi d^3 / (6 mu0)."""
    return remanence * math.pi * diameter**3 / (6.0 * MU0)


def cuboid_moment(a, b, c, remanence):
    """Moment (A m^2) of a uniformly magnetised a x b x c cuboid: Br a b c / mu0."""
    return remanence * a * b * c / MU0


def legacy_seed_moment(b_max, height):
    """The seed paper's moment formula ``Bmax 4 pi (h/2)^3 / (2 mu0)``.

    Offered only to reproduce that paper's numbers. It equals ``Br V / mu0`` only
    for a cylinder whose diameter equals its length (``h = D = L``); it is 1.5x too
    large for a sphere of diameter ``h`` and off by ``(L/D)^2`` for other cylinders
    (with ``h = L``). Prefer ``cylinder_moment``/``sphere_moment``/``cuboid_moment``.
    """
    return b_max * 4.0 * math.pi * (0.5 * height) ** 3 / (2.0 * MU0)


_SHAPE_DIMENSION_COUNT = {"cylinder": 2, "sphere": 1, "cuboid": 3}


@dataclasses.dataclass
class MagnetGeometry:
    """Shape and material of a permanent magnet, from which its moment follows.

    YAML-loadable (``yaml_load_typed``): only plain fields, all with defaults. The
    defaults are an N52 cylinder of 101.6 x 101.6 mm (4 x 4 in), m ~ 970 A m^2.
    """

    # "cylinder" (magnetised along its axis), "sphere" or "cuboid" (along c).
    shape: str = "cylinder"
    # Metres. cylinder: [diameter, length]; sphere: [diameter]; cuboid: [a, b, c].
    dimensions: list[float] = dataclasses.field(
        default_factory=lambda: [0.1016, 0.1016]
    )
    # Remanence Br in tesla (N52 ~1.43-1.48 T; the seed paper calls it Bmax).
    remanence: float = 1.48
    # Use the seed paper's formula (``legacy_seed_moment``) with h = the last
    # dimension (cylinder length, sphere diameter, cuboid c). Only to reproduce
    # the paper's numbers; wrong unless the shape is a D = L cylinder.
    legacy: bool = False

    def moment(self) -> float:
        """Dipole moment magnitude in A m^2."""
        expected = _SHAPE_DIMENSION_COUNT.get(self.shape)
        if expected is None:
            raise ValueError(
                f"MagnetGeometry.shape must be one of {sorted(_SHAPE_DIMENSION_COUNT)},"
                f" got {self.shape!r}"
            )
        dims = [float(d) for d in self.dimensions]
        if len(dims) != expected or min(dims) <= 0.0:
            raise ValueError(
                f"A {self.shape} needs {expected} positive dimension(s), got {dims}"
            )
        if self.legacy:
            return legacy_seed_moment(self.remanence, dims[-1])
        if self.shape == "cylinder":
            return cylinder_moment(dims[0], dims[1], self.remanence)
        if self.shape == "sphere":
            return sphere_moment(dims[0], self.remanence)
        return cuboid_moment(dims[0], dims[1], dims[2], self.remanence)


# Bounds of a magnet's geometry (check_magnet_geometry).
MIN_REMANENCE, MAX_REMANENCE = 0.1, 1.6
"""Remanence range (T): from the weakest permanent magnets (bonded and flexible ferrites,
0.15-0.25 T; sintered ferrite 0.2-0.45 T) to the saturation polarisation of Nd2Fe14B, the
strongest magnet material, 1.61 T (N52 grades reach 1.43-1.48 T). Zero would be no magnet,
and a negative one the same magnet turned round (its pose says which way it points)."""
MIN_MAGNET_SIZE = 1e-4
"""Smallest dimension (m) of a magnet: 0.1 mm, well below any capsule's magnet."""
MAX_MAGNET_SIZE = 0.5
"""Largest dimension (m): EPMs for capsule endoscopy are 5-15 cm; a 50 cm block of NdFeB
would weigh 0.7-1 t."""


def check_magnet_geometry(geometry: "MagnetGeometry") -> None:
    """Raises ValueError naming the first impossible field (relative to the magnet: the
    caller says which one): a known shape, its number of dimensions, each in
    [MIN_MAGNET_SIZE, MAX_MAGNET_SIZE], and a remanence in [MIN_REMANENCE, MAX_REMANENCE].
    With those, the moment is positive and finite (a remanence of 0 gave a magnet without
    a moment, and no word)."""
    expected = _SHAPE_DIMENSION_COUNT.get(geometry.shape)
    if expected is None:
        raise ValueError(f"shape must be one of {', '.join(sorted(_SHAPE_DIMENSION_COUNT))}, "
                         f"got {geometry.shape!r}")
    if len(geometry.dimensions) != expected:
        raise ValueError(f"dimensions must be {expected} number(s) for a {geometry.shape} "
                         f"(cylinder: [diameter, length], sphere: [diameter], cuboid: "
                         f"[a, b, c]), got {geometry.dimensions!r}")
    need_range(geometry.dimensions, "dimensions", f"[{MIN_MAGNET_SIZE:g}, {MAX_MAGNET_SIZE:g}]",
               "m")
    need_range(geometry.remanence, "remanence", f"[{MIN_REMANENCE:g}, {MAX_REMANENCE:g}]", "T",
               "from ferrite to Nd2Fe14B, which saturates at 1.61 T; the direction is the "
               "pose's")


# --- Finite-size source: the exact field of a uniformly magnetised cylinder -------------
# At the EPM's working distances the point dipole is off by 18 % at 10 cm and 3 % at 20 cm
# (docs/sources.md section 1: almost all of it the EPM's finite size). The cylinder's exact field
# (magpylib's closed form) with the capsule's magnet kept a point dipole (its own size costs
# ~0.1 %) removes that error. Float only: magpylib does not carry derivatives, so the
# linearisation uses the dipole model.

# Step of the central differences that give the force from the field (m): the field's
# relative curvature over it is ~(step / r)^2 ~ 1e-7 at the working distances.
FINITE_DIFFERENCE_STEP = 2e-5
_STENCIL = np.vstack([np.zeros(3), np.eye(3), -np.eye(3)]) * FINITE_DIFFERENCE_STEP


def _frame_along(axis):
    """A rotation matrix whose third column is the unit vector `axis`."""
    zx, zy, zz = (float(v) for v in axis)
    # x = helper x z, with the helper a world axis far from z.
    if abs(zx) < 0.9:  # helper (1, 0, 0)
        x = (0.0, -zz, zy)
    else:  # helper (0, 1, 0)
        x = (zz, 0.0, -zx)
    n = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
    xx, xy, xz = x[0] / n, x[1] / n, x[2] / n
    return np.array([[xx, zy * xz - zz * xy, zx],
                     [xy, zz * xx - zx * xz, zy],
                     [xz, zx * xy - zy * xx, zz]])


def cylinder_field(m_source, offsets, diameter: float, length: float) -> np.ndarray:
    """Field (T) of a cylinder magnetised along its axis, with moment m_source (A m^2,
    along the axis; its size sets the polarisation m mu0 / V), at `offsets` (n x 3, m)
    from its centre (world frame). The closed form of Derby & Olbert (Am. J. Phys. 78,
    2010), as magpylib's core implements it."""
    from magpylib.core import magnet_cylinder_axial_Bfield

    m_source = np.asarray(m_source, dtype=float)
    moment = float(np.linalg.norm(m_source))
    offsets = np.atleast_2d(np.asarray(offsets, dtype=float))
    if moment == 0.0:
        return np.zeros_like(offsets)
    R = _frame_along(m_source / moment)
    radius = 0.5 * diameter
    polarisation = MU0 * moment / (math.pi * radius * radius * length)
    local = offsets @ R
    rho = np.hypot(local[:, 0], local[:, 1])
    B_rho, _, B_z = magnet_cylinder_axial_Bfield(
        z0=np.full(len(local), 0.5 * length / radius), r=rho / radius, z=local[:, 2] / radius)
    # The radial component along (x, y) / rho; zero on the axis.
    scale = polarisation * np.divide(B_rho, rho, out=np.zeros_like(rho), where=rho > 0.0)
    B_local = np.column_stack([scale * local[:, 0], scale * local[:, 1], polarisation * B_z])
    return B_local @ R.T


def _cylinder_quadrature(axis, diameter: float, length: float, rings: int, around: int,
                         layers: int):
    """Points (offsets from the centre, world frame) and weights (summing to 1) that
    integrate a smooth function over a cylinder's volume: Gauss-Legendre in the axial
    coordinate (`layers`) and in the squared radius (`rings`, so equal area), `around`
    equally spaced angles (staggered ring to ring). rings=1, around=4, layers=2 is exact to
    third degree."""
    points, weights = _local_cylinder_quadrature(diameter, length, rings, around, layers)
    return points @ _frame_along(axis).T, weights


@functools.lru_cache(maxsize=32)
def _local_cylinder_quadrature(diameter, length, rings, around, layers):
    """`_cylinder_quadrature` in the cylinder's frame (axis z)."""
    gz, wz = np.polynomial.legendre.leggauss(layers)
    gs, ws = np.polynomial.legendre.leggauss(rings)
    points, weights = [], []
    for z, w_z in zip(gz, wz):
        for k, (s, w_s) in enumerate(zip(0.5 * (gs + 1.0), 0.5 * ws)):
            r = 0.5 * diameter * math.sqrt(s)
            for j in range(around):
                angle = 2.0 * math.pi * (j + 0.5 * (k % 2)) / around
                points.append([r * math.cos(angle), r * math.sin(angle), 0.5 * length * z])
                weights.append(0.5 * w_z * w_s / around)
    return np.array(points), np.array(weights)


# Quadrature of the capsule's magnet, by its clearance from the source (beyond its own
# reach): its centre alone beyond 5 cm (the point target is then within 0.2 % in force and
# 0.6 % in torque of the meshed reference), 8 points beyond twice its reach, 96 closer
# (near the source's rim, where its field varies fastest, the 8-point rule is off by up to
# ~4 % when the two magnets all but touch; measured).
_POINT_CLEARANCE = 0.05
_COARSE_RULE = (1, 4, 2)
_FINE_RULE = (3, 8, 4)


def _clearance(p_local, diameter: float, length: float) -> float:
    """Distance from a point (source frame, axis z) to a solid cylinder centred there."""
    radial = max(math.hypot(p_local[0], p_local[1]) - 0.5 * diameter, 0.0)
    axial = max(abs(p_local[2]) - 0.5 * length, 0.0)
    return math.hypot(radial, axial)


def cylinder_pair_interaction_float(m_source, m_target, p, diameter: float, length: float,
                                    target_size=None, min_distance=DEFAULT_MIN_DISTANCE):
    """``dipole_pair_interaction_float`` with the source a finite cylinder (its exact field,
    `cylinder_field`) and the target at offset p from the source's centre.

    The target is a point dipole, or with `target_size` = (diameter, length) a uniformly
    magnetised cylinder along m_target, its volume integrated by an 8-point rule, or a
    96-point one within twice its size of the source, or its centre alone more than 5 cm
    clear of it (`_cylinder_quadrature`; at 8 cm from the EPM the point target is off by up
    to ~1 %, more where the two all but touch).
    Force on each point: grad (m_i . B) by central differences of the exact field; torque
    on the target about its centre: sum of m_i x B + r_i x F_i. The source gets -F and,
    about its centre, -T - p x F (the pair's total force and torque vanish, as for two
    dipoles). The target's field at the source is its dipole field. Inside the cylinder's
    bounding sphere (no real pair gets there) it falls back to the point dipoles. Returns
    3-tuples of floats.
    """
    p = np.asarray(p, dtype=float)
    if float(np.linalg.norm(p)) <= 0.5 * math.hypot(diameter, length):
        return dipole_pair_interaction_float(m_source, m_target, tuple(p), min_distance)
    m_t = np.asarray(m_target, dtype=float)
    size = float(np.linalg.norm(m_t))
    if target_size is None or size == 0.0:
        points, weights = np.zeros((1, 3)), np.ones(1)
    else:
        m_s = np.asarray(m_source, dtype=float)
        axis = m_s / max(float(np.linalg.norm(m_s)), 1e-300)
        along = float(p @ axis)
        p_local = (math.sqrt(max(float(p @ p) - along * along, 0.0)), 0.0, along)
        reach = 0.5 * math.hypot(*target_size)
        clear = _clearance(p_local, diameter, length) - reach
        if clear > _POINT_CLEARANCE:
            points, weights = np.zeros((1, 3)), np.ones(1)
        else:
            points, weights = _cylinder_quadrature(
                m_t / size, *target_size, *(_FINE_RULE if clear < 2.0 * reach else _COARSE_RULE))
    n = len(points)
    observers = ((p + points)[:, None, :] + _STENCIL[None, :, :]).reshape(-1, 3)
    B = cylinder_field(m_source, observers, diameter, length).reshape(n, len(_STENCIL), 3)
    energy = B @ m_t
    forces = weights[:, None] * (energy[:, 1:4] - energy[:, 4:7]) / (
        2.0 * FINITE_DIFFERENCE_STEP)
    force = forces.sum(axis=0)
    field = weights @ B[:, 0]
    # m_t x field + sum of r_i x F_i (the antisymmetric part of sum F_i r_i^T), then the
    # source's -T - p x F.
    M = forces.T @ points
    lever = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    torque = _cross(m_t, field) + lever
    back = dipole_field(m_t, -p, min_distance)
    source_torque = -torque - _cross(p, force)
    return DipolePairInteraction(tuple(field.tolist()), tuple(np.asarray(back, float).tolist()),
                                 tuple(force.tolist()), tuple(torque.tolist()),
                                 tuple((-force).tolist()), tuple(source_torque.tolist()))


def meshed_reference_wrench(m_source, m_target, p, source_cylinder, target_cylinder,
                            meshing=(24, 8, 12)):
    """A second route to the force and torque (about its centre) on a cylinder magnet from
    another: magpylib's `getFT`, the target cut into `meshing` (around, radial, axial)
    cells, the source's exact field. Cylinders are [diameter, length], magnetised along
    their moments (A m^2); p is the target's centre from the source's. For tests and
    benchmarks: ~10-50 ms a call."""
    import magpylib
    from scipy.spatial.transform import Rotation

    def cylinder(moment, size, position):
        moment = np.asarray(moment, dtype=float)
        size_m = float(np.linalg.norm(moment))
        volume = math.pi * (0.5 * size[0]) ** 2 * size[1]
        orientation = Rotation.align_vectors([moment / size_m], [[0.0, 0.0, 1.0]])[0]
        return magpylib.magnet.Cylinder(dimension=tuple(size),
                                        polarization=(0.0, 0.0, MU0 * size_m / volume),
                                        position=position, orientation=orientation)

    source = cylinder(m_source, source_cylinder, (0.0, 0.0, 0.0))
    target = cylinder(m_target, target_cylinder, np.asarray(p, dtype=float))
    force, torque = magpylib.getFT(source, target, meshing=tuple(meshing), eps=1e-6)
    return np.asarray(force), np.asarray(torque)
