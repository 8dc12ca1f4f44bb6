"""The compliant wall: a colon wall of the thickness and moduli that were measured, lying on
what holds it from outside (`contact: !CompliantWall {}`).

The mechanics, and why. Under the capsule the wall is pushed outward by w over a patch a few
millimetres wide. Three things resist, the first two in parallel, the third in series:

- the wall's hoop stretch: a tube of radius R pushed out by w stretches round by w / R, so a
  wall of thickness h and circumferential modulus E_theta pulls back with a pressure
  E_theta h w / R^2 (a thin-walled tube in hoop tension: the elastic foundation a cylindrical
  shell's hoop stiffness gives, exact for a uniform radial displacement);
- what lies outside the wall (mesentery, fat, the neighbouring bowel, the abdominal wall),
  an elastic foundation of modulus k_support (Pa/m). No source read here gives it: it is an
  assumption (U), swept;
- the wall's own thickness, compressed by E_through / h: 250 times stiffer than the other
  two at the nominal figures, so it barely counts.

So the wall is a Winkler foundation of modulus k = 1 / (1 / (E_theta h / R^2 + k_support) +
h / E_through) (Pa/m) to the capsule (`foundation_modulus`). Two realisations
(`realisation`):

- "foundation" (the default, foundation.py): the foundation integrated over the capsule's
  surface against the colon's wall table, its springs along the wall's normal, so its force
  is k times the capsule's volume beyond the undeformed mucosa (`displaced_volume_force`,
  matched within 4 % from 0.2 mm to half buried: tests/test_foundation.py);
- "hydroelastic": Drake's hydroelastic contact of a compliant layer on the capsule against the
  rigid wall mesh (the same mesh as the rigid wall's): the capsule's pressure field is
  E_h (r - d) / r at distance d from its axis, so E_h = k r gives the pressure k times the
  depth to which the wall's surface cuts into the capsule along the capsule's normal
  (`capsule_modulus`); its closed form `indentation_force`, matched within 5 % from 0.3 to
  4 mm on the mesh of the capsule's field (capsule_field.py; tests/test_contact_models.py).
  The two agree at small indentations and part by 10 % at 2 mm; the hydroelastic one costs
  three to four times as much a step (the soft wall's patch is hundreds of contact polygons).

The wall stiffens as it stretches (foundation realisation): intestine's stress-strain curve
is bilinear, its circumferential modulus 7.7 times higher past a knee (Terry 2014, pig small
intestine, biaxial). Past the depth knee_strain x R beyond the mucosa (hoop strain
knee_strain) the foundation's modulus is the one with the circumferential modulus
`stiffening` times higher, so the pressure is k d, then k knee + k2 (d - knee); its closed
form `bilinear_volume_force` (tests/test_foundation.py). Where the knee lies no source read
here says (U, swept in benchmarks/bench_tissue.py): at 0.25 it leaves the nominal wall's
runs as they were (their 99th percentile of the capsule's depth, 2.8 mm, is a hoop strain
near 0.14-0.19) and holds a soft wall's capsule under a magnet's newton at 8 mm instead of
14 (bench_tissue (d)).

The camera's walls, the lumen truth and coverage are unchanged by either. The hydroelastic
layer is r deep; the foundation pushes deeper too (the cells that face the wall). A capsule
farther out than the wall stretches round before it tears (FAILURE_STRAIN times the lumen's
radius) has gone through it: the run guard's `wall_allowance`.

What it leaves out, and says so: one modulus for the whole colon (R is the colon's median
lumen radius; the hoop term differs by segment as 1 / R^2); under a local load the wall also
bends and ovalises, which the hoop term (exact for a uniform expansion) does not see; the
rate dependence of the moduli (the nominal ones are Massalou's at 1 cm/s, a dragged capsule's
speed; at 10 cm/s the circumferential modulus is 3.4 times higher) and the tissue's
relaxation. Sources and status of every figure: docs/sources.md section 3.5.
"""


import dataclasses
import math

import numpy as np

from capsule_drake.blocks import block
from capsule_drake.physics.contact.capsule_field import capsule_field_mesh
from capsule_drake.physics.contact.foundation import FoundationContact, WallTable
from capsule_drake.physics.contact.tissue import patient_wall
from capsule_drake.physics.contact.common import (add_capsule_drag, add_rigid_hydroelastic_wall,
                                                  contact_properties, set_capsule_field_mesh)
from capsule_drake.schema import need_range


FAILURE_STRAIN = 0.6281
"""The colon wall's elongation at failure: 62.81 %, human, uniaxial (Christensen et al. 2015,
docs/sources.md section 3.5). How far the wall can be pushed out (the run guard's allowance)."""


@dataclasses.dataclass
class CompliantWall:
    """The colon wall yields: a wall of measured thickness and moduli on an elastic support
    (module docstring), with the colon's measured friction. Every figure's source and
    status: docs/sources.md section 3.5."""

    # Thickness of the wall (m): 2.61 mm (SD 1.29), healthy controls, 20 MHz endoscopic
    # mini-probe ultrasound in vivo (Surg Laparosc Endosc Percutan Tech 25:205, 2015).
    thickness: float = 2.61e-3
    # Tensile modulus around the colon (Pa): 0.63 MPa (SD 1.25) circumferential, human
    # colon, uniaxial at 1 cm/s (Massalou et al., J Biomech 91:102, 2019).
    circumferential_modulus: float = 0.63e6
    # Modulus through the wall's thickness, in compression (Pa): no compression data were
    # read; taken as the longitudinal tensile modulus, 1.76 MPa at 1 cm/s (Massalou 2019).
    # Assumption (U); it barely counts (in series with a far softer foundation).
    through_thickness_modulus: float = 1.76e6
    # What holds the wall from outside, as an elastic foundation (Pa/m). No source: an
    # assumption (U), to be swept. 3e5 Pa/m is soft tissue of a
    # few kPa loaded over a centimetre.
    support_stiffness: float = 3.0e5
    # Radius of the lumen in the hoop term (m); 0: the colon's median lumen radius.
    lumen_radius: float = 0.0
    # The wall stiffens as it stretches: past a hoop strain of `knee_strain` (the capsule
    # knee_strain x R beyond the mucosa) its circumferential modulus is `stiffening` times
    # the one above. 7.71 is the ratio of the high to the low region of the bilinear fit
    # around the bowel, 1388.89 / 180.07 kPa (Terry et al., IJECB 2(4), 2014; pig small
    # intestine, biaxial after preconditioning): a surrogate (S). Where the knee lies no
    # source read here gives (U): 0.25, swept 0.1-0.4 (benchmarks/bench_tissue.py). 1: no
    # stiffening. The foundation realisation only (Drake's hydroelastic field is linear).
    knee_strain: float = 0.25
    stiffening: float = 7.71
    # Coulomb friction between capsule and mucosa (dynamic = static): 0.09, a colonoscope
    # shaft on human colonic mucosa at the best lubricant (Watanabe et al., Commun Eng 2024;
    # the lowest reached). On small-bowel mucosa 0.0004-0.054 (Lyle et al. 2013).
    friction: float = 0.09
    # Adhesion energy between capsule and mucosa (J/m^2): a cell that has touched the wall
    # stays stuck until pulled sqrt(2 W / k) beyond it (foundation.py). 0.55 J/m^2 is the
    # peel energy of capsule materials on pig small-bowel mucosa (0.055 +- 0.016 mJ/cm^2;
    # tack 0.198 +- 0.070 mJ/cm^2), excised, at room temperature (Terry et al., JMBBM 15:24,
    # 2012): a surrogate (S). The foundation realisation only (Drake's hydroelastic contact
    # has none).
    adhesion_energy: float = 0.55
    # Hunt-Crossley dissipation of the contact (s/m): the tissue's viscous loss. No source
    # read gives it for colon (U).
    hunt_crossley_dissipation: float = 5.0
    # A linear damping of the capsule's velocity on its floating joint (N s/m, N m s/rad);
    # 0: none (no measurement supports one for the colon).
    drag_translational: float = 0.0
    drag_rotational: float = 0.0
    # How the wall's force is computed: "foundation" (the default; foundation.py: the
    # foundation integrated over the capsule's surface against the colon's wall table, its
    # force k times the capsule's volume beyond the mucosa; 1.1-1.7x the rigid stand-in's
    # speed) or "hydroelastic" (Drake's hydroelastic contact of the capsule's field mesh
    # against the wall mesh, its pressure k times the depth along the capsule's normal;
    # 0.3x the rigid stand-in's speed, kept for comparison).
    realisation: str = "foundation"

    def label(self) -> str:
        """How a printed contact figure names the model it comes from."""
        return "compliant wall"

    @property
    def pressure_field(self) -> bool:
        """Whether the contact has a pressure field: always (hydroelastic)."""
        return True

    def step_bound(self, capsule) -> tuple[float, str]:
        """(longest plant step in s, why) of the model's own (physics/step_bound.py): none.
        The foundation's force is linearly implicit in the wall's own stiffness, damping and
        friction (foundation.py), stable at any step as Drake's implicit contact is; how far
        a step carries the capsule into the wall is physics/step_bound.py's own bound."""
        return math.inf, ""

    def wall_allowance(self, capsule_radius: float, colon=None) -> float:
        """How far (m) the capsule may be beyond the wall's undeformed surface because the
        wall gave: as far as the wall stretches round before it tears, FAILURE_STRAIN times
        the lumen's radius (a wall pushed out by w stretches by w / R), and at least the
        capsule's radius (the hydroelastic layer's depth). The run guard adds it to its
        `max_wall_excursion`; a capsule farther out has gone through the wall."""
        radius = self.lumen_radius or (median_lumen_radius(colon) if colon is not None
                                       else capsule_radius)
        return max(capsule_radius, FAILURE_STRAIN * radius)

    def wall_tears(self) -> bool:
        """Yes: a capsule beyond `wall_allowance` (and the guard's margin) has stretched
        the wall past its failure strain, which a patient's wall would not survive: the run
        guard ends the run as a perforation ("wall_torn"), its figures up to it standing.
        (A diverging integration is reported as diverged, not torn: it passes the guard's
        speed check within a few steps, and the wall check defers to that check on a state
        that fails both, io/guard.py.)"""
        return True


def hoop_modulus(config: CompliantWall, radius: float) -> float:
    """The wall's hoop stretch as a foundation (Pa/m): E_theta h / R^2."""
    return config.circumferential_modulus * config.thickness / radius**2


def foundation_modulus(config: CompliantWall, radius: float, stiffened: bool = False) -> float:
    """The Winkler modulus the wall presents to the capsule (Pa/m): the hoop stretch and the
    support in parallel, in series with the wall's thickness compressed. `stiffened`: past
    the knee of the wall's stretch (its circumferential modulus `stiffening` times higher)."""
    hoop = hoop_modulus(config, radius) * (config.stiffening if stiffened else 1.0)
    outward = hoop + config.support_stiffness
    through = config.through_thickness_modulus / config.thickness
    return 1.0 / (1.0 / outward + 1.0 / through)


def knee_depth(config: CompliantWall, radius: float) -> float:
    """How far beyond the mucosa (m) the wall stiffens: its knee strain times the lumen's
    radius (a uniform expansion by w stretches the wall round by w / R)."""
    return config.knee_strain * radius if config.stiffening != 1.0 else math.inf


def bilinear_volume_force(k: float, k_stiff: float, knee: float, depth, radius: float,
                          length: float):
    """The force (N) of a wall whose pressure is k d up to `knee` beyond the mucosa and
    k_stiff beyond it, on a capsule `depth` into it, flat: k times the capsule's volume
    beyond the mucosa plus (k_stiff - k) times its volume beyond the knee's surface (a
    surface `knee` deeper), each `displaced_volume_force`'s. The foundation realisation's
    closed form."""
    depth = np.asarray(depth, dtype=float)
    beyond = displaced_volume_force(1.0, depth, radius, length)
    past = (displaced_volume_force(1.0, np.maximum(depth - knee, 0.0), radius, length)
            if math.isfinite(knee) else 0.0)
    return k * beyond + (k_stiff - k) * past


def capsule_modulus(k: float, capsule_radius: float) -> float:
    """The hydroelastic modulus (Pa) of the capsule's layer that makes its pressure k times
    the depth to which the wall cuts into it (Drake's capsule field: E (r - d) / r)."""
    return k * capsule_radius


def indentation_force(k: float, depth, radius: float, length: float):
    """Force (N) with which a Winkler wall of modulus k (Pa/m), flat, pushes back on a
    capsule (radius, cylinder length; m) lying along it and pressed `depth` (m) into it, the
    pressure k times the depth measured along the capsule's normal:
        cylinder: k L (a r - c^2 asinh(a / c)),
        caps (one sphere between them): 2 pi k (r a^2 / 2 - ((a^2 + c^2)^(3/2) - c^3) / 3),
    with c = r - depth the axis's height over the wall and a = sqrt(r^2 - c^2) the half
    width of the contact. From integrating k (r - dist to the axis) over the contact patch;
    the capsule's axis at most r into the wall (its layer's depth)."""
    depth = np.clip(np.asarray(depth, dtype=float), 0.0, radius)
    c = radius - depth
    a = np.sqrt(np.maximum(radius**2 - c**2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        asinh = np.where(c > 0.0, np.arcsinh(np.where(c > 0.0, a / np.maximum(c, 1e-300), 0.0)),
                         0.0)
    cylinder = length * (a * radius - c**2 * asinh)
    caps = 2.0 * math.pi * (radius * a**2 / 2.0 - ((a**2 + c**2) ** 1.5 - c**3) / 3.0)
    return k * (cylinder + caps)


def displaced_volume_force(k: float, depth, radius: float, length: float):
    """Force (N) with which a Winkler wall of modulus k (Pa/m), flat, its springs along its
    normal, pushes back on a capsule (radius, cylinder length; m) lying along it and pressed
    `depth` (m) into it: k times the capsule's volume beyond the wall,
        cylinder: k L (r^2 acos(c / r) - c a),  caps (one sphere's): k pi d^2 (3 r - d) / 3,
    with c = r - depth and a = sqrt(r^2 - c^2). The foundation realisation's closed form
    (foundation.py); `indentation_force` is the hydroelastic one's, whose pressure follows
    the depth along the capsule's normal instead: the two agree at small indentations and
    part by 10 % at 2 mm. Deeper than the radius, the cells that face the wall push: the
    half capsule's volume plus the depth past the axis times its shadow, 2 r L + pi r^2."""
    whole = np.maximum(np.asarray(depth, dtype=float), 0.0)
    depth = np.minimum(whole, radius)
    c = radius - depth
    a = np.sqrt(np.maximum(radius**2 - c**2, 0.0))
    cylinder = length * (radius**2 * np.arccos(np.clip(c / radius, -1.0, 1.0)) - c * a)
    caps = math.pi * depth**2 * (3.0 * radius - depth) / 3.0
    shadow = (whole - depth) * (2.0 * radius * length + math.pi * radius**2)
    return k * (cylinder + caps + shadow)


def wall_lumen_radius(config: CompliantWall, colon) -> float:
    """The lumen radius (m) of the hoop term and the knee: the config's, or the colon's
    median."""
    return config.lumen_radius or median_lumen_radius(colon)


def median_lumen_radius(colon) -> float:
    """The colon's median lumen radius (m): the median over its centreline of the mean wall
    radius around it."""
    s = np.linspace(0.0, float(colon.centerline.length), 400)
    theta = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    radii = colon.wall_radius(s[:, None], theta[None, :])
    return float(np.median(np.mean(radii, axis=1)))


REALISATIONS = ("foundation", "hydroelastic")



# Bounds of the settings (check_compliant_wall).
def check_compliant_wall(config: CompliantWall, scenario=None) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.thickness, "contact.thickness", "[2e-4, 0.03]", "m",
               "a colon's wall is 1-6 mm thick, 23 mm at most in diverticular disease")
    need_range(config.circumferential_modulus, "contact.circumferential_modulus",
               "[1e3, 1e9]", "Pa", "soft tissue: kPa to tens of MPa")
    need_range(config.through_thickness_modulus, "contact.through_thickness_modulus",
               "[1e3, 1e9]", "Pa")
    need_range(config.support_stiffness, "contact.support_stiffness", "[0, 1e10]", "Pa/m")
    if config.lumen_radius != 0.0:
        need_range(config.lumen_radius, "contact.lumen_radius", "[0.005, 0.1]", "m",
                   "or 0: the colon's median radius")
    need_range(config.friction, "contact.friction", "[0, 2]", "",
               "measured on mucosa: 0.0004-0.09")
    need_range(config.adhesion_energy, "contact.adhesion_energy", "[0, 10]", "J/m^2",
               "measured on mucosa: 0.55 (peel) to 1.98 (tack)")
    need_range(config.hunt_crossley_dissipation, "contact.hunt_crossley_dissipation", ">= 0",
               "s/m")
    need_range(config.knee_strain, "contact.knee_strain", "[0.01, 2]", "",
               "the hoop strain past which the wall stiffens; the colon tears near 1.8")
    need_range(config.stiffening, "contact.stiffening", "[1, 50]", "",
               "1: none; measured 7.7 around the bowel")
    need_range(config.drag_translational, "contact.drag_translational", ">= 0", "N s/m")
    need_range(config.drag_rotational, "contact.drag_rotational", ">= 0", "N m s/rad")
    if config.realisation not in REALISATIONS:
        raise ValueError(f"contact.realisation must be one of {', '.join(REALISATIONS)}, "
                         f"got {config.realisation!r}")
    if config.lumen_radius == 0.0 and config.support_stiffness == 0.0:
        return
    k = foundation_modulus(config, config.lumen_radius or 0.025)
    need_range(k, "contact: the wall's foundation modulus", "[1e3, 1e11]", "Pa/m",
               "from its thickness, moduli and support")


def add_compliant_contact(plant, scene_graph, colon_params, colon, config: CompliantWall,
                          capsule_radius: float, capsule_length: float) -> float:
    """Before Finalize, after every other model: the capsule's compliant layer of modulus
    k r (k the wall's foundation modulus at the colon's lumen radius, r the capsule's)
    against the polyps' hulls and the boxes closing the tube, and (realisation
    "hydroelastic") against the wall's rigid mesh too; the drag. Returns k (Pa/m)."""

    def properties():
        return contact_properties(config.friction, config.hunt_crossley_dissipation)

    if config.realisation == "hydroelastic":
        add_rigid_hydroelastic_wall(plant, colon_params, colon, properties)
    else:
        add_rigid_hydroelastic_wall(plant, colon_params, colon, properties, chunks=False)
    k = foundation_modulus(config, wall_lumen_radius(config, colon))
    set_capsule_field_mesh(plant, scene_graph, properties,
                           capsule_field_mesh(capsule_radius, capsule_length),
                           capsule_modulus(k, capsule_radius))
    add_capsule_drag(plant, config.drag_translational, config.drag_rotational)
    return k


def add_compliant_wall(parts, config: CompliantWall) -> None:
    """The "contact" block's models: `add_compliant_contact` in the station, with the
    patient's wall when the colon comes from the population (tissue.py `patient_wall`);
    shares the wall's foundation modulus as contact.foundation_modulus."""
    config = patient_wall(config, parts.colon_params)
    parts.share("contact.wall_config", config)
    parts.share("contact.foundation_modulus", add_compliant_contact(
        parts.plant, parts.scene_graph, parts.colon_params, parts.colon, config,
        parts.capsule.radius, parts.capsule.length))


@block("contact", CompliantWall, check=check_compliant_wall, models=add_compliant_wall,
       where="")
def add_foundation(builder, parts, config: CompliantWall) -> None:
    """After Finalize (realisation "foundation"): the wall's force on the capsule
    (FoundationContact) among the applied forces; exports contact.wall (WallContact)."""
    if config.realisation != "foundation":
        return
    config = parts.shared("contact.wall_config")        # the patient's
    plant = parts.plant
    body = parts.capsule_body
    inspector = parts.scene_graph.model_inspector()
    shell = [g for g in plant.GetCollisionGeometriesForBody(body)
             if inspector.GetName(g).endswith("shell_field")]
    X_BG = inspector.GetPoseInFrame(shell[0])
    axial = body.default_rotational_inertia().get_moments()[2]
    table = WallTable(parts.colon)
    radius = wall_lumen_radius(config, parts.colon)
    system = builder.AddNamedSystem("wall_contact", FoundationContact(
        body.index(), table, X_BG, parts.capsule.radius,
        parts.capsule.length, parts.shared("contact.foundation_modulus"), config.friction,
        config.hunt_crossley_dissipation, plant.time_step(), body.default_mass(), axial,
        body.default_spatial_inertia().CopyToFullMatrix6(),
        body.default_spatial_inertia().get_com(),
        plant.gravity_field().gravity_vector(), table.nearest(parts.X_WB0.translation()),
        config.adhesion_energy, knee_depth=knee_depth(config, radius),
        stiffened_modulus=foundation_modulus(config, radius, stiffened=True)))
    builder.Connect(parts.output("capsule.state"), system.GetInputPort("capsule_state"))
    # The other applied forces pass through it (its force is implicit in the wall's own
    # response, exact at rest only with the others known): the applied_forces block.
    parts.applied_through = (system.GetInputPort("other_forces"),
                             system.GetOutputPort("applied_spatial_force"))
    parts.export(system.GetOutputPort("wall_contact"), "contact.wall")
