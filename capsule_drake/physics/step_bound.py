"""The longest plant time step a scenario's physics allows, and why (`time_step_bound`).

Pure and fast (no plant, no colon: the scenario's numbers and models/capsule.sdf, read once):
`scenario.validate` calls it and refuses a longer `plant.time_step` with one line.

How Drake steps this plant
--------------------------
A discrete MultibodyPlant with a SAP-family solver ("lagged", "sap", "similar") solves, each
step, the momentum balance  M (v - v0) = dt k(x0) + J^T gamma  (joint damping, hence the
capsule's drag, taken implicitly) and then  q = q0 + dt N(q0) v  (Drake's
CompliantContactManager: "k(x0) are all the non-constraint forces such as Coriolis terms and
external actuation, evaluated at the previous state x0"; Castro et al., "An unconstrained
convex formulation of compliant contact", IEEE T-RO 2022). So:

- the contact impulses gamma are implicit (a convex problem: stable for any stiffness);
- the magnet's force and torque reach the plant through its applied-spatial-force input,
  computed from the state at the start of the step (physics/magnet_force.py): they are
  *explicit*, and the magnet coupling is integrated by symplectic (semi-implicit) Euler.

1. The magnet coupling: stability and accuracy of explicit Euler
----------------------------------------------------------------
Near its equilibrium the capsule is a spring-mass system of the magnet's stiffness. For
x'' = -omega^2 x, one symplectic Euler step maps (x, v) by [[1 - h^2, dt], [-omega^2 dt, 1]],
h = omega dt: determinant 1, trace 2 - h^2. For h < 2 the eigenvalues lie on the unit circle
(no growth, no decay) and the oscillation runs at omega_num = 2 asin(h/2) / dt: +1.0 % at
h = 0.5, +4.7 % at h = 1, +57 % at h = 2; for h > 2 one eigenvalue exceeds 1 in magnitude
and the motion diverges at once (tests/test_step_bound.py checks both, on that map and on
Drake's own plant with the magnet system). The bound keeps

    omega dt <= SAFETY * 2,   SAFETY = 1/2,

half the stability limit: the frequency within 5 % of the true one. Measured in the station
(benchmarks/bench_time_step.py, CloseDrag below: the capsule held on the transverse colon's
roof 10.4 cm below the EPM, side-on, omega = 315-344 rad/s by the formula below without and
with its lever terms): the peak spin is within 6 % of the 0.25 ms run's up to a 3 ms step
(omega dt = 0.95-1.03), +12 % at 4 ms, +22 % at 5 ms, +44 % at 6 ms (1.9-2.06), and the run
diverges at 7 ms (2.2-2.4). In Default (20 cm, omega = 116-124 rad/s) a 16 ms step is
omega dt = 1.9-2.0: the peak spin is 8 times the reference's.

omega is the stiffest the coupling can be in this scenario: the capsule's magnet (moment
m_c, at d = 3 mm from the centre of mass) as close to the EPM (moment m_E) as the scenario
lets it come, and the EPM turned for the largest field there:

    r_min = epm.clearance + h_min + depth_min
        h_min: the EPM's centre above its lowest point, at its flattest attitude (the same
               half-extent the EPM's guard keeps clear of the skin: epm/poses.py);
        depth_min: the capsule's centre below the skin: 0 for the procedural patient (its
               transverse colon comes within 0.3-14 mm of the skin over seeds 0-11, so
               nothing is counted), colon.source.skin_above + the capsule's radius for an
               imported colon (its skin is that far above the mesh's highest point);
    B    = 2 (mu0 / 4 pi) m_E / r^3       the dipole's field on its axis, the largest |B|
                                          at distance r (side-on it is half);
    F    = 3 m_c B / r                    the coaxial force, the largest at r;
    K    = 4 F / r                        its gradient (the translational stiffness);
    k_rot = m_c B + 2 F d + K d^2         torque per radian about the centre of mass;
    omega = max(sqrt(k_rot / I), sqrt(K / m))     I, m: transverse inertia, mass
                                                  (models/capsule.sdf: 1.093e-6 kg m^2,
                                                  12 g).

k_rot is U'' for the energy U(theta) = -m_c(theta) . B(p(theta)) of the capsule turned by
theta about its centre of mass: m_c B from the moment turning away from the field; the lever
d adds the field's gradient met by the turning moment as the magnet swings by d, and the pull
acting on the arm d (each ~F d); K d^2 the field's curvature along the swing. The largest
U'' over all attitudes of both magnets, computed numerically (tests/test_step_bound.py), is
m_c B + 2.08 F d, under m_c B + 2 F d + K d^2; Drake's capsule turning on a pin under the
coaxial EPM oscillates within 0.3 % of this omega.

With field_model "finite" the cylinder's exact field is sampled on the plane
clearance + depth_min below the EPM's lowest point, for attitudes from upright to flat;
where it exceeds the dipole's (2-3 cm from a rim: 3 % in Default), B, F and K are scaled up
by that ratio. With magnet_force.apply false
the force is not applied and sets no bound.

Default scenario: r_min = 20 + 50.8 = 70.8 mm, B = 0.547 T, F = 29 N, K = 1.66 kN/m,
k_rot = 0.88 N m/rad, omega = 898 rad/s (translational 371 rad/s): dt <= 1/898 = 1.11 ms.

2. The magnet force held between updates (magnet_force.update_period)
-----------------------------------------------------------------------
A force held for n plant steps (T = n dt) maps (x, v) over a hold by
[[1 - c h^2, T], [-omega^2 T, 1]], h = omega T, c = (n + 1) / (2 n): determinant
1 + (n - 1) h^2 / (2 n) > 1 for every n > 1. A held force feeds energy into the oscillation
at ANY period, at the rate sigma = (n - 1) / (4 n) omega^2 T per second (for small h); only
the contact's friction and the drag take it out. So no hold period is stable in free flight
(measured below: Default's capsule, 20 cm from the EPM, omega ~ 120 rad/s, spins up in its
first drop onto the wall and diverges with a 4 ms hold, omega T ~ 0.5; CloseDrag's with a
2 ms hold, omega T ~ 0.7). `step_bounds(...).force_period` gives the same
explicit-Euler limit for the period the force is held (omega T <= 1); it does not make a
hold safe, and the shipped FastContact (2 ms) and OneOfEverything (4 ms) holds exceed it.

3. The contact: how far a step carries the capsule into the wall
----------------------------------------------------------------
The solver is implicit in contact, so stiffness (the capsule's hydroelastic modulus, the
point stiffness) never makes it unstable: SAP resolves a contact whose time scale
sqrt(m / k) is longer than ~dt / 2 pi and treats a stiffer one as near-rigid (Castro et al.
2022, section V; with the capsule's 12 g, sqrt(m / k) is ~1.1 ms for the 1e4 N/m of two
2e4 N/m point contacts in series and ~0.5 ms for the hydroelastic capsule of modulus 5e6 Pa
pressed on a 20 mm lumen). What a long step does is carry the capsule INTO the wall: a
contact acts only once the geometry query finds it at the start of a step, so a capsule
meeting the wall at v enters it by up to v dt first (measured below: the magnet flings the
Close capsule onto the wall at 2.1-2.5 m/s and its deepest excursion is 1.2 mm at 1 ms,
4.3 mm at 2 ms, one step's travel). Once its centre is past the wall (the hydroelastic
pressure field's medial axis, one radius R = 5.8 mm in; for the convex wall pieces, 3 mm
thick, R + 1.5 mm, where the shortest way out of a piece is through it), the contact pushes
it on through: it tunnels. The bound keeps one step's travel at IMPACT_SPEED = 1 m/s within
CONTACT_TRAVEL = 2 mm:

    dt <= 2 mm / (1 m/s) = 2 ms.

2 mm is a third of the way to tunnelling (R / 3 = 1.9 mm), and what the measurement allows:
at a 2 ms step every case below that the magnet does not fling stays within 1.1 mm of the
wall (ExVivoSegment 1.10 mm: its drop onto the tissue reaches 0.73 m/s), at 4 ms they reach
1.1-1.7 mm, and at 16 ms the capsule goes through the wall (13 mm in Default).

1 m/s: the capsule's drops onto the wall at the start of the shipped scenarios reach
0.47-0.73 m/s (io/guard.py's measurement; 0.60 m/s in Default below), a free fall across the
widest lumen (9 cm, the cecum) 1.3 m/s. The magnet's snap across a lumen 10 cm below the EPM
(Close below: 2.3 m/s) is faster than the bound covers: its overshoot is over 1 mm at 1 ms.
The run guard (io/guard.py) still stops a run that goes through the wall.

4. The implicit magnet torque (magnet_force.implicit, the default)
-------------------------------------------------------------------
With `implicit` the magnet's torque is integrated by backward Euler in its stiff part
(MagneticForce._declare_implicit_torque): no step bound from the turning, which is what sets
omega above (898 rad/s). The pull stays explicit: its stiffness K = 4 F / r gives
omega_translation (371 rad/s at the closest clearance, 2.7 ms), and the contact's 2 ms
(section 3) is then the shorter. Backward Euler damps the magnet's wobble (by 1 / sqrt(1 +
(omega dt)^2) a step) instead of keeping it; the convergence study
(benchmarks/bench_step_convergence.py, docs/results/performance.md, "Time-step convergence")
shows what that costs in the drag.

Measured (benchmarks/bench_time_step.py, 4 s of each case, Drake 1.58)
---------------------------------------------------------------------
Largest excursion of the capsule beyond the colon wall (mm) per plant step (ms), the magnet
force recomputed every step (FastContact: held 2 ms, its own, below 2 ms); * fails (over
1 mm, or the advance off the 0.25 ms run's by over 15 % + 2 mm: none did); x diverged (the
run guard stopped it, or the state went NaN). Close is Default started on the transverse
colon's roof, where the patient is shallowest (the EPM 10.4 cm from the capsule): the
magnet flings the capsule across the lumen at 2.3 m/s. CloseDrag is Close with a
translational drag of 20 N s/m (no fling; the rotation undamped).

    step (ms)       0.25   0.5     1   1.5     2     3     4     5     6     7     8    16
    Default         0.54  0.52  0.49     -  0.46     - 1.25*     -     -     - 1.50*13.14*
    FarMagnet       0.39  0.39  0.44     -  0.38     - 1.65*     -     -     - 2.67* 3.68*
    WithArm         0.54  0.52  0.49     -  0.46     - 1.19*     -     -     - 1.60*     x
    FastContact     0.12  0.10  0.09     -  0.38     -  0.47     -     -     - 1.03*     x
    ExVivoSegment   0.52  0.54  0.54     - 1.10*     - 1.13*     -     -     - 4.20*     x
    Close           0.89  0.90 1.22*  0.88 4.33* 5.23* 1.94*     x     x     x     x     x
    CloseDrag       0.56  0.55  0.55  0.58  0.55  0.55 1.06*  0.55 2.03*     x     x     x
    bound (ms): 1.11 for all but ExVivoSegment, 2 (its magnet, 15.7 cm away, allows 3.9)

    force held (ms) at a 1 ms step     2     4     8    16
    Default                         0.53     x     x     x
    Close                          1.37* 1.91*     x     x
    CloseDrag                          x     x     x     x

Every shipped scenario measured passes beyond its bound (Default, FarMagnet and WithArm to
2 ms, FastContact to 4 ms, against 1.11 ms) but ExVivoSegment, which fails at its bound of
2 ms by 0.1 mm (1.10 mm); Close, whose capsule meets the wall faster than the bound's 1 m/s,
fails at 1 ms (1.22 mm) and 2 ms (4.3 mm). The magnet's own instability (CloseDrag at 7 ms,
Default near 16 ms) sits at omega dt ~ 2 for the geometry each reaches; the bound's omega
(898 rad/s) is that of the closest geometry any scenario can reach, 2.6-2.9 times
CloseDrag's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import xml.etree.ElementTree as ElementTree

import numpy as np

from capsule_drake.epm.poses import magnet_vertical_half_extent
from capsule_drake.models import MODELS_DIR
from capsule_drake.physics.magnetics import MU0, cylinder_field

SAFETY = 0.5
"""Fraction of explicit Euler's stability limit (omega dt = 2) a step may use."""

IMPACT_SPEED = 1.0
"""The fastest the capsule is taken to meet the wall (m/s): the module's section 3."""

CONTACT_TRAVEL = 0.002
"""The farthest one step may carry the capsule at IMPACT_SPEED (m): section 3."""


@dataclasses.dataclass(frozen=True)
class CapsuleInertia:
    """What the bound needs of models/capsule.sdf."""

    mass: float            # kg
    transverse_inertia: float  # kg m^2, about the centre of mass, across the axis
    ipm_offset: float      # m, the IPM's centre from the centre of mass
    radius: float          # m, of the collision capsule
    length: float = 0.0    # m, of its cylinder


@functools.cache
def capsule_inertia() -> CapsuleInertia:
    """Mass, transverse inertia, IPM offset and radius read from models/capsule.sdf."""
    text = (MODELS_DIR / "capsule.sdf").read_text()
    # Drake's own elements carry an undeclared "drake:" prefix: not needed here.
    root = ElementTree.fromstring(text.replace("<drake:", "<drake_").replace("</drake:",
                                                                            "</drake_"))
    link = root.find("./model/link")
    inertial = link.find("inertial")
    mass = float(inertial.findtext("mass"))
    tensor = inertial.find("inertia")
    transverse = max(float(tensor.findtext("ixx")), float(tensor.findtext("iyy")))
    com = [float(x) for x in (inertial.findtext("pose") or "0 0 0 0 0 0").split()[:3]]
    ipm = root.find("./model/frame[@name='ipm']")
    p_BM = [float(x) for x in ipm.findtext("pose").split()[:3]]
    offset = math.dist(p_BM, com)
    radius = float(link.find("./collision/geometry/capsule/radius").text)
    length = float(link.find("./collision/geometry/capsule/length").text)
    return CapsuleInertia(mass, transverse, offset, radius, length)


@dataclasses.dataclass(frozen=True)
class MagnetStiffness:
    """The stiffest the magnet coupling can be, and what it follows from."""

    distance: float         # m, closest EPM-capsule magnet centres
    field: float            # T, largest |B| there
    force: float            # N, largest force there
    force_gradient: float   # N/m
    rotational: float       # N m/rad, about the capsule's centre of mass
    omega_rotation: float   # rad/s
    omega_translation: float  # rad/s

    @property
    def omega(self) -> float:
        return max(self.omega_rotation, self.omega_translation)


def magnet_stiffness(m_epm: float, m_ipm: float, distance: float, capsule: CapsuleInertia,
                     field_scale: float = 1.0) -> MagnetStiffness:
    """The largest stiffness of the dipole coupling at `distance` (m) over both magnets'
    orientations (the module's section 1), its fields and forces scaled by `field_scale`."""
    field = field_scale * 2.0 * (MU0 / (4.0 * math.pi)) * m_epm / distance**3
    force = 3.0 * m_ipm * field / distance
    gradient = 4.0 * force / distance
    d = capsule.ipm_offset
    rotational = m_ipm * field + 2.0 * force * d + gradient * d * d
    return MagnetStiffness(distance, field, force, gradient, rotational,
                           math.sqrt(rotational / capsule.transverse_inertia),
                           math.sqrt(gradient / capsule.mass))


def _half_extent_min(geometry) -> float:
    """The EPM's centre above its lowest point at its flattest attitude (m)."""
    return min(magnet_vertical_half_extent([0.0, 0.0, 1.0], geometry),
               magnet_vertical_half_extent([1.0, 0.0, 0.0], geometry))


def closest_distance(scenario) -> tuple[float, str]:
    """The closest the capsule's magnet can come to the EPM's centre (m), and how it adds up."""
    capsule = capsule_inertia()
    half = _half_extent_min(scenario.epm.magnet)
    clearance = scenario.epm.clearance
    if scenario.colon.procedural:
        depth, depth_text = 0.0, ""
    else:
        depth = scenario.colon.source.skin_above + capsule.radius
        depth_text = f" + {depth * 1e3:.1f} mm skin to capsule centre"
    text = (f"{clearance * 1e3:.0f} mm epm.clearance + {half * 1e3:.1f} mm from the EPM's "
            f"centre to its surface{depth_text}")
    return float(clearance + half + depth), text


@functools.lru_cache(maxsize=32)
def _finite_field_ratio(diameter: float, length: float, moment: float,
                        gap: float) -> float:
    """Largest ratio of a cylinder EPM's exact field to its dipole's on-axis field, on the
    plane `gap` below its lowest point, over attitudes from upright to flat."""
    radius, half_length = 0.5 * diameter, 0.5 * length
    worst = 0.0
    for tilt in np.linspace(0.0, 0.5 * np.pi, 7):
        axis = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
        low = half_length * np.cos(tilt) + radius * np.sin(tilt)
        x = np.linspace(-2.0 * radius, 2.0 * radius, 17)
        points = np.column_stack([x, np.zeros_like(x), np.full_like(x, -(low + gap))])
        B = np.linalg.norm(cylinder_field(moment * axis, points, diameter, length),
                           axis=1)
        r = np.linalg.norm(points, axis=1)
        dipole_axis = 2.0 * (MU0 / (4.0 * np.pi)) * moment / r**3
        worst = max(worst, float(np.max(B / dipole_axis)))
    return worst


@dataclasses.dataclass(frozen=True)
class StepBounds:
    """The longest plant step and force period a scenario allows, with their reasons."""

    plant_step: float        # s: plant.time_step must not exceed it
    plant_why: str
    force_period: float      # s: max(plant.time_step, magnet_force.update_period), see
    force_why: str           # the module's section 2 (a hold is anti-damped at any period)
    magnet_step: float       # s, inf without an applied magnet force
    contact_step: float      # s
    stiffness: MagnetStiffness | None


def _round_down(value: float, digits: int = 3) -> float:
    """`value` rounded down to `digits` significant figures (a bound printed as it is)."""
    if not math.isfinite(value) or value <= 0.0:
        return value
    scale = 10.0 ** (digits - 1 - math.floor(math.log10(value)))
    return math.floor(value * scale * (1 + 1e-12)) / scale


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3g} ms"


def step_bounds(scenario) -> StepBounds:
    """The bounds of the module's sections 1-3 for `scenario` (a loaded Scenario)."""
    capsule = capsule_inertia()
    contact_step = CONTACT_TRAVEL / IMPACT_SPEED
    contact_why = (f"contact: a capsule meeting the wall at {IMPACT_SPEED:g} m/s must not "
                   f"enter it by more than {CONTACT_TRAVEL * 1e3:g} mm in the step before "
                   "the contact acts")
    # The contact model's own part (an explicit wall force: its stiffest mode).
    wall_step, wall_why = scenario.contact.step_bound(capsule)
    if wall_step < contact_step:
        contact_step, contact_why = wall_step, wall_why

    stiffness = None
    magnet_step = math.inf
    magnet_why = "the magnet force is not applied"
    if scenario.magnet_force.apply:
        distance, distance_text = closest_distance(scenario)
        m_epm = scenario.epm.magnet.moment()
        scale = 1.0
        epm = scenario.epm.magnet
        if (scenario.magnet_force.field_model == "finite" and epm.shape == "cylinder"
                and not epm.legacy):
            gap = distance - _half_extent_min(epm)
            scale = max(1.0, _finite_field_ratio(float(epm.dimensions[0]),
                                                 float(epm.dimensions[1]), m_epm, gap))
        stiffness = magnet_stiffness(m_epm, scenario.capsule.ipm.moment(), distance, capsule,
                                     scale)
        implicit = scenario.magnet_force.implicit and scenario.magnet_force.update_period == 0
        if implicit:
            # The torque is implicit (section 4): only the pull stays explicit.
            omega, mode, what = (stiffness.omega_translation, "pulls",
                                 "the magnet's torque is implicit but its pull explicit")
        else:
            omega = stiffness.omega
            mode = ("turns" if stiffness.omega_rotation >= stiffness.omega_translation
                    else "pulls")
            what = "the magnet's force is applied explicitly"
        magnet_step = SAFETY * 2.0 / omega
        magnet_why = (f"{what}, and with the EPM "
                      f"{distance * 1e3:.1f} mm away ({distance_text}) its "
                      f"{stiffness.field:.3g} T field {mode} the capsule at up to "
                      f"{omega:.0f} rad/s: explicit Euler needs omega*dt <= "
                      f"{SAFETY * 2:g}, half its stability limit of 2")
    if magnet_step <= contact_step:
        plant_step = magnet_step
        plant_why = f"{magnet_why}; the contact allows {_ms(contact_step)}"
    else:
        plant_step = contact_step
        plant_why = contact_why + (f"; the magnet allows {_ms(magnet_step)}"
                                   if math.isfinite(magnet_step) else "")
    force_why = (magnet_why + "; a force held over several steps is anti-damped at any "
                 "period (only friction and drag stop it)")
    return StepBounds(_round_down(plant_step), plant_why, _round_down(magnet_step), force_why,
                      magnet_step, contact_step, stiffness)


def time_step_bound(scenario) -> tuple[float, str]:
    """(largest plant.time_step in s, why) for `scenario`: the shorter of the magnet
    coupling's explicit-Euler limit and the contact's travel limit (module docstring),
    rounded down to 3 significant figures. `why` completes "... this scenario allows (why)"."""
    bounds = step_bounds(scenario)
    return bounds.plant_step, bounds.plant_why


def update_period_bound(scenario) -> tuple[float, str]:
    """(largest period in s the magnet force may be held, why): compare with
    max(plant.time_step, magnet_force.update_period). See the module's section 2: holding
    the force over several steps feeds energy in at any period."""
    bounds = step_bounds(scenario)
    return bounds.force_period, bounds.force_why
