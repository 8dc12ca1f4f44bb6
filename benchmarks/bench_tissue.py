"""The compliant wall's predictions beside published measurements (issue: tissue from what is
published). Nothing here is fitted to the figure it is set beside.

    python benchmarks/bench_tissue.py [--figure docs/tissue_predictions.png]

(a) Resistance of a 26 x 11 mm capsule pulled along the bowel (Guo et al. 2020, Nonlinear Dyn
    101:65: 7 mN to 4.5 N over the contact conditions and progression speeds they tested, pig
    small intestine). Simulated here: the compliant wall's own route (foundation.py) in a
    straight tube of lumen radius R_l, the capsule (5.5 mm radius, 15 mm of cylinder, 5 g, U:
    the abstract gives no mass) pulled along its axis by a stiff spring whose end moves at the
    speed v; the resistance is the spring's mean force once the capsule slides steadily. The
    wall's modulus is the model's for that lumen (foundation_modulus: the hoop stretch of a
    tube of radius R_l, the support, the thickness), its friction the colon's 0.09. R_l from a
    wide lumen (the capsule lies on the wall under its weight) to a collapsed one narrower
    than the capsule (the wall wraps it: Guo's bowel was not distended), speeds 1 and 10 mm/s.
(b) Burst pressure. A thin-walled tube of radius R and wall thickness h bursts when its hoop
    stress P R / h reaches the wall's ultimate tensile strength: P = sigma_u h / R (Laplace).
    With the wall's figures (h: 2.61 mm, EUS in vivo; sigma_u: 0.87 MPa, human rectum and
    sigmoid, Christensen 2015; 0.9 MPa, human large bowel across, Egorov 2002) and the
    model's lumen radii of the caecum and the sigmoid (the default patient's), beside cadaver
    colons insufflated to rupture: caecum 81 mmHg, sigmoid 169 mmHg ("Air-pressure-induced
    colon injury during diagnostic colonoscopy"). Also with the wall stretched to its failure
    strain before it bursts (62.8 % elongation, Christensen 2015: thinner by 1 / lambda and
    wider by lambda, P / lambda^2), a second reading of the same figures.
(c) Wall stiffness under a colonoscope's head. Johnson et al. 2019 pressed colonoscope heads
    perpendicular into porcine colon: 0.8 N/mm (small head) and 0.7 N/mm (large head,
    angled). The compliant wall's force on a hemispherical head of radius r_h pressed delta
    in is k pi delta^2 (3 r_h - delta) / 3 (the Winkler foundation's spherical cap); its
    secant stiffness F / delta, at depths of 2-6 mm (within the hemisphere), for the head
    radius of a 12-13 mm
    colonoscope (6.25 mm, U: the abstract gives no diameters) and the wall's foundation
    modulus at the nominal support and across the support's sweep (U).

Prints each check's simulated (or computed) figure, the published one, their ratio, and what
would have to change for them to meet.
"""

import dataclasses
import math
import sys

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.multibody.tree import SpatialInertia, UnitInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from capsule_drake.anatomy import load_colon
from capsule_drake.physics.contact.foundation import (FoundationContact, StraightTube,
                                                     WallTable)
from capsule_drake.capsule.model import capsule_model
from capsule_drake.physics.contact.compliant import (FAILURE_STRAIN, CompliantWall,
                                                      bilinear_volume_force,
                                                      foundation_modulus, knee_depth,
                                                      median_lumen_radius)
from capsule_drake.physics.contact.tissue import patient_tissue
from capsule_drake.scenario import load_scenario

MMHG = 133.322
UTS = {"Christensen 2015, human rectum + sigmoid": 0.87e6,
       "Egorov 2002, human large bowel, across": 0.9e6}
FAILURE_STRETCH = 1.6281   # 62.81 % elongation at failure, human (Christensen 2015)
RUPTURE_MMHG = {"cecum": 81.0, "sigmoid": 169.0}
JOHNSON_N_PER_MM = {"small head, straight": 0.8, "large head, angled": 0.7}
HEAD_RADIUS = 0.00625      # m (U): a 12.5 mm colonoscope tip
SUPPORT_SWEEP = (0.0, 1.0e5, 3.0e5, 1.0e6, 3.0e6, 1.0e7)   # Pa/m (U)
KNEE_SWEEP = (0.0, 0.1, 0.25, 0.4)   # the wall's knee_strain (U); 0: no stiffening
GUO_RANGE_N = (0.007, 4.5)
GUO_RADIUS, GUO_CYLINDER, GUO_MASS = 0.0055, 0.015, 0.005   # m, m, kg (mass U)
LUMEN_RADII = (0.020, 0.0060, 0.0055, 0.0050, 0.0045, 0.0040)   # m
SPEEDS = (0.001, 0.010)                                           # m/s
FRICTIONS = (0.007, 0.054, 0.09)       # Lyle 2013 (small bowel) low and high; colon, nominal
ADHESIONS = (0.0, 0.55, 1.98)          # J/m^2: none; Terry 2012 peel (nominal) and tack


class Puller(LeafSystem):
    """A spring (stiffness K, critically damped on the capsule) from the capsule's centre to
    an anchor moving along +x at `speed` from x0: the pull on the capsule."""

    def __init__(self, body_index, x0, speed, stiffness=300.0, mass=GUO_MASS):
        super().__init__()
        self._index, self._x0, self._speed = body_index, x0, speed
        self._k, self._c = stiffness, 2.0 * math.sqrt(stiffness * mass)
        self._state = self.DeclareVectorInputPort("state", 13)
        self.DeclareAbstractOutputPort(
            "force", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]), self._calc)

    def pull(self, context) -> float:
        x = self._state.Eval(context)
        return (self._k * (self._x0 + self._speed * context.get_time() - x[4])
                - self._c * (x[10] - self._speed))

    def _calc(self, context, output):
        force = ExternallyAppliedSpatialForce()
        force.body_index = self._index
        force.p_BoBq_B = np.zeros(3)
        force.F_Bq_W = SpatialForce(np.zeros(3), np.array([self.pull(context), 0.0, 0.0]))
        output.set_value([force])


def pulled_resistance(lumen_radius: float, speed: float, time_step: float = 2e-3,
                      adhesion: float | None = None, friction: float | None = None) -> float:
    """Mean pull (N) on the capsule sliding steadily along a straight tube (module (a)), with
    the wall's adhesion energy `adhesion` (J/m^2) and friction (default: the model's)."""
    nominal = CompliantWall()
    k = foundation_modulus(nominal, lumen_radius)
    adhesion = nominal.adhesion_energy if adhesion is None else adhesion
    friction = nominal.friction if friction is None else friction
    r, L, m = GUO_RADIUS, GUO_CYLINDER, GUO_MASS
    axial = 0.5 * m * r**2
    transverse = m * (3 * r**2 + L**2) / 12.0
    builder = DiagramBuilder()
    plant = builder.AddSystem(MultibodyPlant(time_step))
    body = plant.AddRigidBody("capsule", SpatialInertia(
        m, np.zeros(3), UnitInertia(transverse / m, transverse / m, axial / m)))
    plant.Finalize()
    g = np.array([0.0, 0.0, -9.81])
    wall = builder.AddSystem(FoundationContact(
        body.index(), WallTable(StraightTube(lumen_radius)), RigidTransform(), r, L, k, friction,
        5.0, time_step, m, axial, np.diag([transverse, transverse, axial, m, m, m]),
        gravity_W=g, adhesion_energy=adhesion, knee_depth=knee_depth(nominal, lumen_radius),
        stiffened_modulus=foundation_modulus(nominal, lumen_radius, stiffened=True)))
    puller = builder.AddSystem(Puller(body.index(), 0.05, speed))
    builder.Connect(plant.get_state_output_port(), wall.GetInputPort("capsule_state"))
    builder.Connect(plant.get_state_output_port(), puller.GetInputPort("state"))
    builder.Connect(puller.get_output_port(), wall.GetInputPort("other_forces"))
    builder.Connect(wall.GetOutputPort("applied_spatial_force"),
                    plant.get_applied_spatial_force_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    # Along the tube's axis, resting on its floor (or centred, where it fills the lumen).
    q = RotationMatrix.MakeYRotation(math.pi / 2).ToQuaternion()
    z = -max(lumen_radius - r, 0.0)
    plant.SetPositionsAndVelocities(plant.GetMyMutableContextFromRoot(context), np.r_[
        q.w(), q.x(), q.y(), q.z(), 0.05, 0.0, z, np.zeros(6)])
    # Slide 1 cm (the spring stretched to the resistance first), then average the pull over
    # the next 1 cm of the capsule's travel; a capsule that does not slide within a minute
    # is held harder than the spring can pull (reported as inf).
    puller_context = puller.GetMyContextFromRoot(context)
    plant_context = plant.GetMyContextFromRoot(context)
    pulls = []
    while context.get_time() < 60.0:
        try:
            simulator.AdvanceTo(context.get_time() + 0.002 / speed)  # 2 mm of the anchor's way
        except RuntimeError:      # diverged (a snug lumen's chatter spins the capsule up)
            return math.nan
        x = plant.GetPositionsAndVelocities(plant_context)[4]
        if x > 0.07:
            pulls.append(puller.pull(puller_context))
        if x > 0.08:
            break
    if not pulls:
        return math.inf
    return float(np.mean(pulls))


def segment_radius(colon, name: str) -> float:
    """The mean lumen radius (m) over the middle half of a segment of the model's colon."""
    import numpy as np
    start, end = colon.centerline.segment_ranges()[name]
    s = np.linspace(start + 0.25 * (end - start), end - 0.25 * (end - start), 50)
    theta = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    return float(np.mean(colon.wall_radius(s[:, None], theta[None, :])))


def burst_pressure(sigma_u: float, thickness: float, radius: float) -> float:
    """Laplace's burst pressure (Pa) of a thin-walled tube."""
    return sigma_u * thickness / radius


def head_force(k: float, depth: float, head_radius: float, knee: float = math.inf,
               k_stiff: float = 0.0) -> float:
    """Force (N) of a Winkler foundation k (Pa/m) on a sphere pressed `depth` (at most its
    radius) into it; past `knee` its pressure rises k_stiff per metre (the stiffened wall:
    the cap beyond the knee's surface counts k_stiff - k more)."""
    def cap(d):
        return math.pi * d**2 * (3.0 * head_radius - d) / 3.0
    past = cap(depth - knee) if depth > knee else 0.0
    return k * cap(depth) + (k_stiff - k) * past


def sink_depth(config, radius: float, force: float) -> float:
    """How deep (m) a capsule lying along a flat stretch of the wall of `config` (lumen
    radius `radius` for the hoop term and the knee) sinks under `force` (N): the bilinear
    closed form solved by bisection."""
    model = capsule_model()
    k, k2 = foundation_modulus(config, radius), foundation_modulus(config, radius, True)
    knee = knee_depth(config, radius)
    low, high = 0.0, 0.2
    for _ in range(80):
        mid = 0.5 * (low + high)
        if bilinear_volume_force(k, k2, knee, mid, model.radius, model.length) < force:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def main() -> int:
    figure = sys.argv[sys.argv.index("--figure") + 1] if "--figure" in sys.argv else None
    rows_a, rows_b, rows_c, rows_d = [], [], [], []
    scenario = load_scenario()
    colon, _ = load_colon(scenario.colon)
    wall = CompliantWall()
    print("(a) resistance of a 26 x 11 mm capsule pulled along a straight tube, beside Guo et "
          "al. 2020's 7 mN - 4.5 N")
    print("| lumen radius (mm) | k (Pa/m) | speed (mm/s) | resistance (N) | beside 7 mN | "
          "beside 4.5 N |")
    print("|---|---|---|---|---|---|")
    for lumen in LUMEN_RADII:
        k = foundation_modulus(wall, lumen)
        for speed in SPEEDS:
            force = pulled_resistance(lumen, speed)
            rows_a.append((lumen, speed, force))
            print(f"| {lumen * 1000:.1f} | {k:.2e} | {speed * 1000:.0f} | {force:.4f} | "
                  f"{force / GUO_RANGE_N[0]:.2f} | {force / GUO_RANGE_N[1]:.2f} |", flush=True)
    print("The wide lumen's is Coulomb's mu m g (the capsule on the wall under its weight); a "
          "lumen narrower than the capsule wraps it, and the wall's hoop stretch (1 / R^2) "
          "presses it all round.\n")
    print("(a') the same pull in the wide lumen (20 mm) across the measured friction and "
          "adhesion: mu from small bowel (Lyle 2013: 0.007, 0.054) to colon (0.09, nominal), "
          "adhesion none, peel (0.55 J/m^2, nominal) and tack (1.98 J/m^2, Terry 2012)")
    print("| friction | adhesion (J/m^2) | 1 mm/s (N) | 10 mm/s (N) | beside 7 mN (1 mm/s) |")
    print("|---|---|---|---|---|")
    for mu in FRICTIONS:
        for energy in ADHESIONS:
            slow, fast = (pulled_resistance(0.020, v, adhesion=energy, friction=mu)
                          for v in SPEEDS)
            print(f"| {mu} | {energy} | {slow:.4f} | {fast:.4f} | "
                  f"{slow / GUO_RANGE_N[0]:.2f} |", flush=True)
    print("Adhesion holds the cells at the contact's edge to the wall (a spring in tension "
          "until pulled sqrt(2 W / k) off): more normal force, more friction. Peel and tack "
          "give the same pull in steady sliding (the stuck cells never reach their release "
          "distance); they part when the capsule is lifted off.\n")
    print("(b) burst pressure, Laplace P = sigma_u h / R, beside cadaver colons insufflated to "
          "rupture")
    print("| segment | R (mm) | strength | P (mmHg) | stretched to failure (mmHg) | measured "
          "(mmHg) | ratio | ratio stretched |")
    print("|---|---|---|---|---|---|---|---|")
    for segment, measured in RUPTURE_MMHG.items():
        radius = segment_radius(colon, segment)
        for source, sigma in UTS.items():
            p = burst_pressure(sigma, wall.thickness, radius) / MMHG
            stretched = p / FAILURE_STRETCH**2
            rows_b.append((segment, source, p, stretched, measured))
            print(f"| {segment} | {radius * 1000:.1f} | {sigma / 1e6:.2f} MPa ({source}) | "
                  f"{p:.0f} | {stretched:.0f} | {measured:.0f} | {p / measured:.2f} | "
                  f"{stretched / measured:.2f} |")
    print("To meet at the caecum with these strengths the wall would be thinner at rupture or "
          "the lumen wider than the model's: h / R smaller by the ratio.\n")

    radius = median_lumen_radius(colon)
    print(f"(c) wall stiffness under a colonoscope's head (r_h = {HEAD_RADIUS * 1000:.2f} mm, U), "
          f"secant F / delta, the colon's median lumen radius {radius * 1000:.1f} mm")
    print("| support (Pa/m) | k (Pa/m) | F/d at 2 mm | 4 mm | 6 mm (N/mm) | measured (N/mm) | "
          "ratio at 4 mm |")
    print("|---|---|---|---|---|---|---|")
    for support in SUPPORT_SWEEP:
        swept = CompliantWall(support_stiffness=support)
        k = foundation_modulus(swept, radius)
        stiff = dict(knee=knee_depth(swept, radius),
                     k_stiff=foundation_modulus(swept, radius, stiffened=True))
        secants = [head_force(k, d, HEAD_RADIUS, **stiff) / (d * 1000)
                   for d in (0.002, 0.004, 0.006)]
        nominal = " (nominal)" if support == wall.support_stiffness else ""
        measured = JOHNSON_N_PER_MM["small head, straight"]
        rows_c.append((support, secants[1], measured))
        print(f"| {support:.0e}{nominal} | {k:.2e} | {secants[0]:.3f} | {secants[1]:.3f} | "
              f"{secants[2]:.3f} | {measured} | {secants[1] / measured:.2f} |")
    print("Johnson's samples' support is not in the abstract: a sample on a rigid plate is held "
          "by its thickness alone (E / h = "
          f"{wall.through_thickness_modulus / wall.thickness:.1e} Pa/m), far stiffer.")
    print(f"(c') the same at the nominal support across the knee of the wall's stretch "
          f"(knee_strain, U; the knee {radius * 1000:.1f} mm x strain beyond the mucosa)")
    print("| knee strain | knee (mm) | F/d at 2 mm | 4 mm | 6 mm (N/mm) | ratio at 4 mm |")
    print("|---|---|---|---|---|---|")
    for strain in KNEE_SWEEP:
        swept = CompliantWall(knee_strain=strain or 1.0, stiffening=wall.stiffening
                              if strain else 1.0)
        k = foundation_modulus(swept, radius)
        stiff = dict(knee=knee_depth(swept, radius),
                     k_stiff=foundation_modulus(swept, radius, stiffened=True))
        secants = [head_force(k, d, HEAD_RADIUS, **stiff) / (d * 1000)
                   for d in (0.002, 0.004, 0.006)]
        label = ("none (linear)" if not strain
                 else f"{strain}" + (" (nominal)" if strain == wall.knee_strain else ""))
        knee = f"{stiff['knee'] * 1000:.1f}" if strain else "-"
        print(f"| {label} | {knee} | {secants[0]:.3f} | {secants[1]:.3f} | {secants[2]:.3f} | "
              f"{secants[1] / JOHNSON_N_PER_MM['small head, straight']:.2f} |")

    print(f"\n(d) how deep a capsule sinks into the wall under a steady pull (a magnet's), "
          f"lying along it, the colon's median lumen radius {radius * 1000:.1f} mm: the "
          "nominal wall and the population's corners (5th / 95th percentiles), linear and "
          "across the knee (U)")
    print("| wall | k (Pa/m) | knee strain | 0.5 N (mm) | 1 N (mm) | 2 N (mm) |")
    print("|---|---|---|---|---|---|")
    for name in ("nominal", "soft", "stiff"):
        base = (wall if name == "nominal"
                else dataclasses.replace(wall, **patient_tissue(0, name).values))
        for strain in KNEE_SWEEP:
            swept = dataclasses.replace(base, knee_strain=strain or 1.0,
                                        stiffening=base.stiffening if strain else 1.0)
            depths = [sink_depth(swept, radius, f) * 1000 for f in (0.5, 1.0, 2.0)]
            rows_d.append((name, strain, depths))
            print(f"| {name} | {foundation_modulus(swept, radius):.2e} | "
                  f"{strain or 'none (linear)'} | {depths[0]:.1f} | {depths[1]:.1f} | "
                  f"{depths[2]:.1f} |")
    print("The run guard allows the wall's failure strain (62.81 %) times the lumen radius "
          f"beyond the undeformed wall for its give ({FAILURE_STRAIN * radius * 1000:.1f} mm "
          "here; compliant.py wall_allowance), plus its 5 mm margin.")
    if figure:
        plot(figure, rows_a, rows_b, rows_c)
        print(f"figure: {figure}")
    return 0


def plot(path, rows_a, rows_b, rows_c) -> None:
    """The three checks beside their measurements, one panel each."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    ax.axhspan(*GUO_RANGE_N, color="0.85", label="Guo 2020: 7 mN - 4.5 N")
    for speed, marker in zip(SPEEDS, ("o", "s")):
        pts = [(lumen * 1e3, force) for lumen, v, force in rows_a if v == speed and force > 0]
        ax.plot(*zip(*pts), marker=marker, label=f"model, {speed * 1e3:.0f} mm/s")
    ax.axvline(GUO_RADIUS * 1e3, color="k", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("lumen radius (mm); dotted: the capsule's")
    ax.set_ylabel("resistance (N)")
    ax.set_title("(a) a 26 x 11 mm capsule pulled along")
    ax.legend(fontsize=8)
    ax = axes[1]
    labels = [f"{seg}\n{src.split(',')[0]}" for seg, src, *_ in rows_b]
    x = np.arange(len(rows_b))
    ax.bar(x - 0.2, [p for _, _, p, _, _ in rows_b], 0.4, label="model (Laplace)")
    ax.bar(x + 0.2, [q for _, _, _, q, _ in rows_b], 0.4, label="stretched to failure")
    ax.scatter(x, [m for *_, m in rows_b], color="k", zorder=3, label="cadaver rupture")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("burst pressure (mmHg)")
    ax.set_title("(b) the wall's burst pressure")
    ax.legend(fontsize=8)
    ax = axes[2]
    supports = [max(sup, 3e4) for sup, _, _ in rows_c]
    ax.plot(supports, [k for _, k, _ in rows_c], "o-", label="model, secant at 4 mm")
    ax.axhline(rows_c[0][2], color="k", ls="--", label="Johnson 2019: 0.8 N/mm")
    ax.set_xscale("log")
    ax.set_xlabel("support outside the wall (Pa/m, U; 0 drawn at 3e4)")
    ax.set_ylabel("stiffness under a colonoscope's head (N/mm)")
    ax.set_title("(c) the wall under a colonoscope's head")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
