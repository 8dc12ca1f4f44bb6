"""Typed, YAML-loadable parameters of the procedural colon.

Status tags follow docs/sources.md: V = checked in a primary source, S = secondary
source, U = engineering assumption. Every length is in metres, every angle in radians unless
the field name says otherwise.

Sources (numbers quoted in docs/sources.md, section 3 "Colon anatomy and tissue"):
  - total length 150 +- 19 cm (110-196), CT colonography, n = 295 (V).
  - haustral fold height: ascending 14.6, transverse 9.5, descending 6.5 mm (V).
  - segment lengths: cecum 6-8, ascending 15-20, transverse 45-50, descending ~25,
    sigmoid 35-45, rectum 12-15 cm (U).
  - diameters: cecum < 9 cm, ascending ~46 mm, transverse < 6 cm, descending ~29 mm,
    sigmoid 25-40 mm (S/U).
  - fold spacing 2-4 cm, sigmoid with few haustra, 3 taeniae (U/S).
  - abdomen ~20-25 cm front to back supine; depth of the transverse colon ~3-8 cm,
    ascending/descending ~8-12 cm, sigmoid/rectum ~10-15 cm (U).
"""

from dataclasses import dataclass, field

import numpy as np

from capsule_drake.schema import need_range

SEGMENT_NAMES = ("rectum", "sigmoid", "descending", "transverse", "ascending", "cecum")
"""Segments in the order met from the anus (s = 0) to the cecal pole."""

SEXES = ("any", "female", "male")
BOWEL_HABITS = ("any", "daily", "every_2_3_days", "less_often")
SIGMOID_VARIANTS = ("any", "normal", "redundant")


@dataclass
class PopulationParams:
    """Who the patient is: fixed where given, drawn from the population where "any"."""

    # "any" (drawn: women 44 % of the time, anatomy/population.py FEMALE_SHARE), "female"
    # or "male".
    sex: str = "any"
    # "any" (the population's spread), "daily", "every_2_3_days" or "less_often".
    bowel_habit: str = "any"
    # The total length's percentile in the patient's group (0-100), or None: drawn.
    length_percentile: float | None = None
    # "any", "normal" (the sigmoid among the shortest 76 %) or "redundant" (the longest
    # 24 %, anatomy/population.py REDUNDANT_SIGMOID_SHARE).
    sigmoid: str = "any"


def check_population_params(params: PopulationParams) -> None:
    """Raises ValueError naming the first impossible field (as `colon.population.<f>`)."""
    for name, allowed in (("sex", SEXES), ("bowel_habit", BOWEL_HABITS),
                          ("sigmoid", SIGMOID_VARIANTS)):
        value = getattr(params, name)
        if value not in allowed:
            raise ValueError(f"colon.population.{name} must be one of {', '.join(allowed)}, "
                             f"got {value!r}")
    p = params.length_percentile
    if p is not None and not (np.isfinite(p) and 0.0 < p < 100.0):
        raise ValueError(f"colon.population.length_percentile must be in (0, 100) or null, "
                         f"got {p!r}")


@dataclass
class SegmentParams:
    """Dimensions of one colon segment. Lengths are sampled per patient from [min, max]."""

    # Shortest arc length of the segment's centreline [m]; source per segment below.
    length_min: float = 0.15
    # Longest arc length of the segment's centreline [m].
    length_max: float = 0.20
    # Nominal lumen diameter (distended) [m].
    diameter: float = 0.04
    # Haustral fold height as measured (before `ColonParams.fold_height_scale`) [m].
    fold_height: float = 0.0
    # Smallest axial distance between consecutive haustral folds [m].
    fold_spacing_min: float = 0.02
    # Largest axial distance between consecutive haustral folds [m].
    fold_spacing_max: float = 0.04
    # True where the three taeniae run (haustra are crescents between them); the taeniae
    # spread into a continuous layer on the rectum (S).
    has_taeniae: bool = True


def _rectum() -> SegmentParams:
    # Length 12-15 cm (U). Diameter 40 mm: not in the sources, assumed for a distended
    # ampulla (U). No haustra: the rectal valves are modelled separately (ColonParams).
    return SegmentParams(
        length_min=0.12, length_max=0.15, diameter=0.040, fold_height=0.0,
        fold_spacing_min=1.0, fold_spacing_max=1.0, has_taeniae=False)


def _sigmoid() -> SegmentParams:
    # Length 35-45 cm (U); diameter 25-40 mm, 32 mm used (S/U). "Few haustra" (S): wide
    # spacing 5-8 cm (U); fold height 5 mm, below the descending 6.5 mm (U).
    return SegmentParams(
        length_min=0.35, length_max=0.45, diameter=0.032, fold_height=0.005,
        fold_spacing_min=0.05, fold_spacing_max=0.08)


def _descending() -> SegmentParams:
    # Length ~25 cm, sampled 23-27 cm (U); diameter ~29 mm (S); folds 6.5 mm (V);
    # spacing 2-4 cm (U).
    return SegmentParams(
        length_min=0.23, length_max=0.27, diameter=0.029, fold_height=0.0065,
        fold_spacing_min=0.02, fold_spacing_max=0.04)


def _transverse() -> SegmentParams:
    # Length 45-50 cm, the longest (U); diameter < 6 cm, 50 mm used (S/U); folds 9.5 mm
    # (V); spacing 2-4 cm (U).
    return SegmentParams(
        length_min=0.45, length_max=0.50, diameter=0.050, fold_height=0.0095,
        fold_spacing_min=0.02, fold_spacing_max=0.04)


def _ascending() -> SegmentParams:
    # Length 15-20 cm (U); diameter ~46 mm (S); folds 14.6 mm (V); spacing 2-4 cm (U).
    return SegmentParams(
        length_min=0.15, length_max=0.20, diameter=0.046, fold_height=0.0146,
        fold_spacing_min=0.02, fold_spacing_max=0.04)


def _cecum() -> SegmentParams:
    # Length 6-8 cm (U); the widest segment, < 9 cm: 70 mm used (S/U); fold height taken
    # as the ascending colon's 14.6 mm (U); spacing 2-3 cm (U).
    return SegmentParams(
        length_min=0.06, length_max=0.08, diameter=0.070, fold_height=0.0146,
        fold_spacing_min=0.02, fold_spacing_max=0.03)


@dataclass
class AbdomenParams:
    """Anterior abdominal wall of a supine patient (table top z = 0, +y toward the head)."""

    # Skin height above the table at the umbilicus = front-to-back size [m]; 20-25 cm (U).
    depth_at_umbilicus: float = 0.22
    # Skin height above the table at the pubic symphysis [m] (U).
    depth_at_pubis: float = 0.175
    # Skin height above the table at the xiphoid [m] (U).
    depth_at_xiphoid: float = 0.20
    # Height of the flank line (widest point of the torso cross-section) [m] (U).
    flank_height: float = 0.11
    # Half width of the torso at the flank line [m] (U).
    half_width: float = 0.18
    # y of the umbilicus [m]; the world origin is placed there (convention).
    umbilicus_y: float = 0.0
    # y of the pubic symphysis [m] (U).
    pubis_y: float = -0.17
    # y of the xiphoid process [m] (U).
    xiphoid_y: float = 0.20
    # y range of the displayed torso mesh [m] (display only).
    torso_y_min: float = -0.26
    torso_y_max: float = 0.30


@dataclass
class MucosaParams:
    """Look of the mucosa: a seeded procedural texture (see `anatomy.texture`) and the
    material's sheen. Colours are RGB in [0, 1] as stored in the PNG (display values)."""

    # Mean colour of the mucosa between vessels: salmon pink-red as seen in white-light
    # colonoscopy (U).
    base_color: list[float] = field(default_factory=lambda: [0.86, 0.46, 0.40])
    # Strength of the low-frequency colour variation: patches up to this fraction of the way
    # toward a paler and toward a redder tint (about +-2 sigma) [-] (U).
    variation_amplitude: float = 0.25
    # Size of those patches (correlation length along the wall) [m] (U).
    variation_scale: float = 0.006
    # Relative brightness noise of the fine granular grain (crypt openings, texel-size) [-] (U).
    grain_amplitude: float = 0.035
    # Fraction of the mucosa covered by visible submucosal vessels [-] (U).
    vessel_density: float = 0.07
    # Colour of the superficial vessels: darker red with a purple cast (U).
    vessel_color: list[float] = field(default_factory=lambda: [0.55, 0.12, 0.20])
    # Colour of the deeper vessels, seen through more tissue: bluish purple, blurrier (U).
    deep_vessel_color: list[float] = field(default_factory=lambda: [0.62, 0.30, 0.40])
    # Share of the vessel trees drawn in the deep layer [-] (U).
    deep_fraction: float = 0.4
    # Diameter of a vessel tree's trunk where it enters the view [m]: submucosal vessels of
    # a few tenths of a millimetre, branching down to capillary size (U).
    vessel_width: float = 0.0006
    # Texture resolution: texels around the lumen (image width; u = theta / 2 pi spans it
    # once, so the texel size around scales with the lumen's circumference).
    texels_around: int = 512
    # Texture resolution along the axis (image height); the pattern repeats every
    # texels_along / texels_per_metre metres along the centreline (0.57 m by default).
    texels_along: int = 2048
    # Texels per metre of arc length along the axis. 3600 makes texels square where the
    # lumen's circumference is texels_around / 3600 = 0.14 m (a 45 mm diameter).
    texels_per_metre: float = 3600.0
    # Specular colour (grey level of Ks) of the wet surface: a moderate highlight [-] (U).
    specular: float = 0.35
    # Phong exponent (Ns) of that highlight: larger is a smaller, sharper spot [-] (U).
    shininess: float = 40.0


@dataclass
class ColonParams:
    """Everything that defines one procedural colon. Same params -> same colon."""

    # Patient seed: segment lengths, landmark jitter and fold placement derive from it.
    seed: int = 0

    rectum: SegmentParams = field(default_factory=_rectum)
    sigmoid: SegmentParams = field(default_factory=_sigmoid)
    descending: SegmentParams = field(default_factory=_descending)
    transverse: SegmentParams = field(default_factory=_transverse)
    ascending: SegmentParams = field(default_factory=_ascending)
    cecum: SegmentParams = field(default_factory=_cecum)

    # Multiplies every measured fold height: an insufflated colon during a procedure has
    # lower folds than the measured ones [-] (U).
    fold_height_scale: float = 0.5
    # Per-fold random height factor is uniform in [1 - jitter, 1 + jitter] [-] (U).
    fold_height_jitter: float = 0.25
    # Half width of a haustral fold's raised-cosine axial profile [m]: folds are ~1 cm
    # wide at the base (U).
    fold_half_width: float = 0.006
    # Random axial shift of each crescent relative to its neighbours around the lumen:
    # haustra of the three sectors are staggered [m] (U).
    fold_stagger: float = 0.004
    # Taeniae: angle of the first band in the rotation-minimising frame [rad] (U); the
    # other two follow at +120 and +240 degrees (S).
    taenia_angle: float = 0.5
    # Height of the inward ridge along each taenia [m] (U).
    taenia_height: float = 0.001
    # Width (Gaussian sigma, along the wall) of the taenia ridge [m]; bands are ~8 mm (U).
    taenia_width: float = 0.003
    # Rectal (Houston) valves: distances from the anus [m]; three valves at ~5-11 cm (S/U).
    rectal_valve_positions: list[float] = field(
        default_factory=lambda: [0.055, 0.08, 0.105])
    # Rectal valve height before `fold_height_scale` [m] (U).
    rectal_valve_height: float = 0.008
    # Distance over which the nominal radius blends between segments [m] (U).
    radius_blend_length: float = 0.04
    # A patient drawn from the population (anatomy/population.py): given, the segments'
    # lengths and diameters above are replaced by the patient's of this seed; null (the
    # default), they are used as they are.
    population: PopulationParams | None = None

    # Standard deviation of the random offset of every course landmark [m] (U).
    landmark_jitter: float = 0.008
    # Gaussian smoothing (sigma, along the arc) of the landmark spline [m]: rounds the
    # flexures so their radius of curvature stays above the lumen radius (U).
    course_smoothing: float = 0.025
    # Centreline sampling step [m].
    centerline_step: float = 0.001

    # Collision mesh: largest axial step between rings [m].
    collision_axial_step: float = 0.004
    # Largest gap between a collision edge and the analytic wall along the axis [m]: rings
    # crowd (down to `collision_min_step`) where folds curve the wall; 0 spaces them
    # uniformly at `collision_axial_step`, which then leaves up to ~1.3 mm at the
    # ascending colon's fold crests.
    collision_tolerance: float = 0.0003
    # Smallest axial step between collision rings [m].
    collision_min_step: float = 0.001
    # Collision mesh vertices per ring.
    collision_points_around: int = 32
    # Visual mesh: largest axial step between rings [m]; rings crowd where folds curve the
    # wall, so that straight edges stay within `visual_tolerance` of it (down to
    # `visual_min_step`), as for the collision mesh; and vertices per ring. Meshcat and
    # recordings draw it.
    visual_axial_step: float = 0.004
    visual_tolerance: float = 0.0001
    visual_min_step: float = 0.00075
    visual_points_around: int = 48
    # Camera mesh: the textured wall the capsule camera renders, with the same meaning of
    # the fields. A software render costs in proportion to the triangles it is given, so
    # by default it has the collision mesh's resolution: the camera sees the surface the
    # capsule touches, and the texture carries the fine detail.
    camera_axial_step: float = 0.004
    camera_tolerance: float = 0.0003
    camera_min_step: float = 0.001
    camera_points_around: int = 32
    # Number of OBJ files the collision tube is split into along its length.
    collision_chunks: int = 15

    abdomen: AbdomenParams = field(default_factory=AbdomenParams)
    # Texture and sheen of the visual wall (no effect on contact).
    mucosa: MucosaParams = field(default_factory=MucosaParams)

    # Where the colon comes from: "procedural" (the fields above build it), "ex_vivo" (the
    # shipped reconstruction of a porcine tissue segment lying in a tray, generated by code;
    # anatomy/ex_vivo.py), or the path of a mesh (OBJ, STL, PLY, GLB) or of a folder
    # written by `capsule-sim import-colon`. An imported colon keeps only `seed` (the
    # ex vivo segment's), `collision_chunks`, `mucosa` (for a mesh without a texture) and
    # the `mesh_*` fields below; arc length starts at its narrower end.
    source: str = "procedural"
    # Scale applied to an imported mesh's coordinates (0.001 for one in millimetres).
    mesh_scale: float = 1.0
    # An imported mesh with more triangles is decimated to this many (a software camera
    # render costs per triangle).
    mesh_max_faces: int = 150000
    # Start the imported centreline at the wider end instead.
    mesh_reverse: bool = False
    # There is no abdomen around an imported mesh: the EPM keeps its clearance from a flat
    # surface this far above the mesh's highest point [m] (an abdominal wall; a few mm for
    # tissue in a tray).
    mesh_skin_above: float = 0.02

    def segment(self, name: str) -> SegmentParams:
        """The parameters of the segment called `name` (one of SEGMENT_NAMES)."""
        if name not in SEGMENT_NAMES:
            raise KeyError(f"unknown colon segment {name!r}")
        return getattr(self, name)


# Bounds of the colon's parameters (check_colon_params), each with its reason.
DIAMETER_RANGE = {
    # Human colon diameters, distended: ~2.5-9 cm (cecum < 9 cm, transverse < 6 cm,
    # ascending ~46 mm, descending ~29 mm, sigmoid 25-40 mm; S/U, module docstring). The
    # lower bound, 2 cm for every segment, leaves the 11.6 mm capsule room between its
    # folds. The upper bounds are the anatomy's, capped where the procedural course (fixed
    # landmarks, 40 jittered attempts) still finds room for its loops: wider, the build
    # spends ~10 s failing (measured for seeds 0-3 with each bound alone and all together).
    "rectum": (0.02, 0.06),
    "sigmoid": (0.02, 0.045),
    "descending": (0.02, 0.045),
    "transverse": (0.02, 0.06),
    "ascending": (0.02, 0.06),
    "cecum": (0.02, 0.09),
}
MAX_SEGMENT_LENGTH = 1.0
"""Longest segment (m): the whole colon is 1.1-2 m (docs/sources.md section 3), its longest
segment (the transverse) 45-50 cm."""
MIN_SEGMENT_LENGTH = 0.02
"""Shortest segment (m): the cecum, the shortest, is 6-8 cm."""
MIN_FOLD_SPACING = 0.005
"""Closest haustral folds (m): folds are ~1 cm wide at the base, so 5 mm apart they overlap;
the fold count (colon length / spacing) stays in the hundreds."""
MIN_CENTERLINE_STEP = 2.5e-4
"""Finest centreline sampling (m): the course check compares every pair of samples within
~10 cm, whose number grows as 1 / step^2 (300,000 pairs at the default 1 mm, 5 million at
0.25 mm)."""
MAX_MESH_VERTICES = 2_000_000
"""Most vertices of each wall mesh (collision, visual, camera), estimated as the longest
colon the segments allow over the ring spacing (the smallest step where a tolerance lets
rings crowd) times the points around: the defaults are 50,000-100,000."""
SEED_RANGE = "[0, 4294967295]"
"""Seeds are 32-bit, as the sensors' (Drake's RandomGenerator keeps 32 bits of its seed)."""


def check_colon_params(params: ColonParams) -> None:
    """Raises ValueError naming the first field (as `colon.<path>`) with an impossible value,
    or one outside the wide anatomical and resource bounds above (every number is finite:
    the scenario checks that first)."""
    def need(ok: bool, path: str, what: str, value):
        if not ok:
            raise ValueError(f"colon.{path} {what}, got {value!r}")

    def bound(path: str, interval: str, unit: str = "", why: str = ""):
        value = params
        for part in path.split("."):
            value = getattr(value, part)
        need_range(value, f"colon.{path}", interval, unit, why)

    bound("seed", SEED_RANGE, "", "a 32-bit seed")
    if params.population is not None:
        check_population_params(params.population)
        need(params.source == "procedural", "population",
             "draws a procedural colon's anatomy: it needs colon.source procedural",
             params.source)
    bound("fold_height_scale", "[0, 2]", "", "insufflation lowers the measured folds")
    need(0 <= params.fold_height_jitter < 1, "fold_height_jitter", "must be in [0, 1)",
         params.fold_height_jitter)
    for name in SEGMENT_NAMES:
        seg = params.segment(name)
        bound(f"{name}.length_min", f"[{MIN_SEGMENT_LENGTH:g}, {MAX_SEGMENT_LENGTH:g}]", "m")
        need(seg.length_max >= seg.length_min, f"{name}.length_max",
             f"must be >= length_min ({seg.length_min})", seg.length_max)
        bound(f"{name}.length_max", f"[{MIN_SEGMENT_LENGTH:g}, {MAX_SEGMENT_LENGTH:g}]", "m")
        low, high = DIAMETER_RANGE[name]
        bound(f"{name}.diameter", f"[{low:g}, {high:g}]", "m",
              f"{_ANATOMY[name]}; the procedural course has room up to {high * 100:g} cm")
        bound(f"{name}.fold_height", ">= 0", "m")
        need(seg.fold_height * params.fold_height_scale * (1 + params.fold_height_jitter)
             < 0.5 * seg.diameter, f"{name}.fold_height",
             "(after fold_height_scale and jitter) must stay below the lumen radius",
             seg.fold_height)
        bound(f"{name}.fold_spacing_min", f">= {MIN_FOLD_SPACING:g}", "m",
              "folds are ~1 cm wide at the base")
        need(seg.fold_spacing_max >= seg.fold_spacing_min, f"{name}.fold_spacing_max",
             f"must be >= fold_spacing_min ({seg.fold_spacing_min})", seg.fold_spacing_max)
    bound("fold_half_width", "[0.001, 0.05]", "m", "folds are ~1 cm wide at the base")
    bound("fold_stagger", "[0, 0.05]", "m")
    bound("taenia_height", "[0, 0.005]", "m")
    bound("taenia_width", "(0, 0.05]", "m", "the bands are ~8 mm wide")
    need(len(params.rectal_valve_positions) <= 10, "rectal_valve_positions",
         "must hold at most 10 valves (there are three)", params.rectal_valve_positions)
    bound("rectal_valve_positions", "[0, 0.3]", "m", "the valves sit 5-11 cm from the anus")
    bound("rectal_valve_height", ">= 0", "m")
    need(params.rectal_valve_height * params.fold_height_scale * (1 + params.fold_height_jitter)
         < 0.5 * params.rectum.diameter, "rectal_valve_height",
         "(after fold_height_scale and jitter) must stay below the rectum's radius",
         params.rectal_valve_height)
    bound("radius_blend_length", "[0.001, 0.2]", "m")
    bound("landmark_jitter", "[0, 0.015]", "m",
          "larger, the course's 40 attempts fail to find a course without kinks or overlaps")
    bound("course_smoothing", "[0.005, 0.1]", "m")
    bound("centerline_step", f"[{MIN_CENTERLINE_STEP:g}, 0.005]", "m")
    longest = sum(params.segment(name).length_max for name in SEGMENT_NAMES)
    for mesh in ("collision", "visual", "camera"):
        axial, low = (getattr(params, f"{mesh}_{item}") for item in ("axial_step", "min_step"))
        tolerance = getattr(params, f"{mesh}_tolerance")
        around = getattr(params, f"{mesh}_points_around")
        bound(f"{mesh}_axial_step", "[1e-4, 0.02]", "m")
        bound(f"{mesh}_min_step", "[1e-4, 0.02]", "m")
        need(low <= axial, f"{mesh}_min_step", f"must be <= {mesh}_axial_step ({axial})", low)
        bound(f"{mesh}_tolerance", "[0, 0.005]", "m")
        need(8 <= around <= 1024, f"{mesh}_points_around", "must be in [8, 1024]", around)
        step = f"{mesh}_min_step" if tolerance > 0 else f"{mesh}_axial_step"
        vertices = longest / getattr(params, step) * around
        need(vertices <= MAX_MESH_VERTICES, f"{mesh}_points_around",
             f"x rings (a colon of up to {longest:.2f} m over {step} "
             f"{getattr(params, step):g} m) must stay below {MAX_MESH_VERTICES:,} vertices, "
             f"not {vertices:,.0f}", around)
    need(1 <= params.collision_chunks <= 100, "collision_chunks",
         "must be in [1, 100] (each is a mesh file and a geometry)", params.collision_chunks)
    a = params.abdomen
    bound("abdomen.depth_at_umbilicus", "[0.12, 0.5]", "m",
          "a supine abdomen is 20-25 cm front to back")
    bound("abdomen.depth_at_pubis", "[0.08, 0.5]", "m")
    bound("abdomen.depth_at_xiphoid", "[0.08, 0.5]", "m")
    bound("abdomen.flank_height", "[0.02, 0.4]", "m")
    need(a.flank_height + 0.01 < min(a.depth_at_umbilicus, a.depth_at_pubis,
                                     a.depth_at_xiphoid),
         "abdomen.flank_height", "must be at least 1 cm below every skin depth", a.flank_height)
    bound("abdomen.half_width", "[0.08, 0.4]", "m")
    for field_name in ("umbilicus_y", "pubis_y", "xiphoid_y", "torso_y_min", "torso_y_max"):
        bound(f"abdomen.{field_name}", "[-1, 1]", "m")
    need(a.pubis_y < a.umbilicus_y < a.xiphoid_y, "abdomen.umbilicus_y",
         f"must lie between pubis_y ({a.pubis_y}) and xiphoid_y ({a.xiphoid_y})",
         a.umbilicus_y)
    need(a.torso_y_min < a.torso_y_max, "abdomen.torso_y_max",
         f"must be > torso_y_min ({a.torso_y_min})", a.torso_y_max)
    for field_name in ("centerline_step", "collision_axial_step", "collision_min_step",
                       "visual_axial_step", "visual_min_step", "camera_axial_step",
                       "camera_min_step", "course_smoothing"):
        value = getattr(params, field_name)
        need(value > 0, field_name, "must be > 0", value)
    if params.source not in ("procedural", "ex_vivo"):
        from pathlib import Path

        source = Path(params.source)
        need(source.is_file() or source.is_dir(), "source",
             "must be procedural, ex_vivo, or an existing mesh file or import folder",
             params.source)
    bound("mesh_scale", "[1e-6, 1e3]", "", "0.001 for a mesh in millimetres")
    need(1000 <= params.mesh_max_faces <= 2_000_000, "mesh_max_faces",
         "must be in [1000, 2000000] (a software camera render costs per triangle)",
         params.mesh_max_faces)
    bound("mesh_skin_above", "[0, 0.5]", "m")
    m = params.mucosa
    for field_name in ("base_color", "vessel_color", "deep_vessel_color"):
        value = getattr(m, field_name)
        need(len(value) == 3 and all(0.0 <= c <= 1.0 for c in value),
             f"mucosa.{field_name}", "must be three values in [0, 1]", value)
    for field_name in ("texels_around", "texels_along"):
        value = getattr(m, field_name)
        need(16 <= value <= 8192, f"mucosa.{field_name}", "must be in [16, 8192]", value)
    bound("mucosa.texels_per_metre", "[1000, 20000]", "1/m",
          "texels of 0.05-1 mm; coarser, the vessels are thinner than a texel")
    bound("mucosa.variation_scale", "[0.001, 0.05]", "m")
    bound("mucosa.variation_amplitude", "[0, 1]")
    bound("mucosa.grain_amplitude", "[0, 1]")
    bound("mucosa.vessel_width", "[0.0002, 0.005]", "m",
          "submucosal vessels are tenths of a millimetre; a trunk must be wider than the "
          "0.1 mm at which a branch ends")
    need(0 <= m.vessel_density <= 0.5, "mucosa.vessel_density", "must be in [0, 0.5]",
         m.vessel_density)
    need(0 <= m.deep_fraction <= 1, "mucosa.deep_fraction", "must be in [0, 1]",
         m.deep_fraction)
    bound("mucosa.specular", "[0, 1]")
    bound("mucosa.shininess", "[0, 1000]", "", "a Phong exponent")


# How wide each segment is, as quoted above (for the diameter bound's message).
_ANATOMY = {"rectum": "a distended rectum is taken as ~4 cm across",
            "sigmoid": "a sigmoid colon is 25-40 mm across",
            "descending": "a descending colon is ~29 mm across",
            "transverse": "a transverse colon is under 6 cm across",
            "ascending": "an ascending colon is ~46 mm across",
            "cecum": "a cecum is under 9 cm across"}

