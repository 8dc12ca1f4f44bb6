"""Procedural colon (rectum to cecum): build from a seed, query the wall, cache meshes.

`build_colon(params)` is pure and deterministic; `procedural_colon_assets(params)` writes its
OBJ/MTL meshes and centreline once per parameter set (anatomy/cache.py) and returns their
paths. Scenarios load a colon of any source through anatomy/source.py.
"""

from pathlib import Path

import numpy as np

from .abdomen import Abdomen
from .centerline import Centerline, rotation_minimising_frame
from .course import nominal_radius, solve_course
from .diverticula import place_diverticula, pouched_chunks, pouched_mesh, pouched_textured
from .lesions import drawn_lesions
from .cache import ColonAssets, asset_paths, build_once, default_cache_root, params_hash, write_asset_files
from .mesh import closed_tube, ring_stations, textured_tube, tube_chunks
from .params import SEGMENT_NAMES, ColonParams
from .lumen_state import narrowed
from .population import resolve_population, shape_params
from .texture import write_mucosa_texture
from .wall import HaustralWall

class TubeColon:
    """What every colon answers, from its `centerline`, its `wall_radius(s, theta)` and its
    `abdomen` (the surface the EPM keeps clear of): the procedural `Colon` and an imported
    one (anatomy/imported.py) alike."""

    centerline: Centerline
    # (extents, centre) boxes around the colon the capsule can touch (e.g. a tray).
    collision_boxes: tuple = ()
    # Pouches cut into its meshes (anatomy/diverticula.py PlacedDiverticulum).
    diverticula: tuple = ()

    def wall_radius(self, s, theta) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def excursion(self, points_W, beyond: float | None = None) -> np.ndarray:
        """How far each world point lies beyond the wall [m] (> 0: inside the tissue).

        Distance to the wall along its normal (to first order) at the closest centreline
        station; beyond the end caps the axial distance past the cap counts too.
        Args: points_W (K, 3) or (3,); beyond: when given, only the points that may lie more
        than this beyond the wall get the distance along the normal, the others their
        radial excursion (at most `beyond`; beyond the wall, an upper bound of the distance):
        which points are past `beyond` is the same, at a fifth of the wall lookups.
        Returns (K,).
        """
        p = np.atleast_2d(np.asarray(points_W, dtype=float))
        cl = self.centerline
        s, dist, theta = cl.closest(p)
        radius = self.wall_radius(s, theta)
        e = dist - radius
        # Radial excursion overstates the distance to a sloped wall (a fold's flank) by
        # 1/cos(slope): divide by |grad F| of F = rho - r(s, theta), the first-order signed
        # distance to the surface rho = r(s, theta) (|grad F| >= 1: the radial excursion
        # bounds it from above where it is positive).
        sloped = np.ones(len(e), bool) if beyond is None else e > beyond
        if np.any(sloped):
            s_, theta_, dist_ = s[sloped], theta[sloped], dist[sloped]
            h_s, h_theta = 2.0e-4, 1.0e-2
            dr_ds = (self.wall_radius(s_ + h_s, theta_)
                     - self.wall_radius(s_ - h_s, theta_)) / (2 * h_s)
            dr_dtheta = (self.wall_radius(s_, theta_ + h_theta)
                         - self.wall_radius(s_, theta_ - h_theta)) / (2 * h_theta)
            slope = np.sqrt(1.0 + dr_ds**2 + (dr_dtheta / np.maximum(dist_, radius[sloped]))**2)
            e[sloped] = e[sloped] / slope
        for s_end, sign in ((0.0, -1.0), (cl.length, 1.0)):
            at_end = s == s_end
            if np.any(at_end):
                t = cl.tangent_at(s_end)
                past = sign * (p[at_end] - cl.point_at(s_end)) @ t
                e[at_end] = np.maximum(e[at_end], past)
        return e

    def depth_below_skin(self, s) -> np.ndarray:
        """Depth [m] of the centreline at arc length s below the anterior skin."""
        return self.abdomen.depth(self.centerline.point_at(np.atleast_1d(s)))

    def segment_lengths(self) -> dict[str, float]:
        """name -> arc length [m] of each segment."""
        return {k: b - a for k, (a, b) in self.centerline.segment_ranges().items()}

    def max_wall_radius(self, s) -> np.ndarray:
        """Largest distance [m] from the centreline to the mucosa around arc length(s) s."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        theta = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
        return np.max(self.wall_radius(s[:, None], theta[None, :]), axis=1)


class Colon(TubeColon):
    """One patient's colon: centreline, analytic wall and abdomen.

    Attributes:
        params: the `ColonParams` it was built from (not mutated).
        centerline: the `Centerline` from the anus (s = 0) to the cecal pole.
        wall: the `HaustralWall` (folds, taeniae, rectal valves).
        abdomen: the `Abdomen` (anterior skin surface).
        target_lengths: sampled length of each segment [m] (the course matches them).
        course: (s, points, boundaries) as solved (`write_course` keeps them with the files).
    """

    def __init__(self, params: ColonParams, centerline: Centerline, wall: HaustralWall,
                 abdomen: Abdomen, target_lengths: dict[str, float], course=None):
        self.params = params
        self.course = course  # (s, points, boundaries) as solved, for write_course
        self.centerline = centerline
        self.wall = wall
        self.abdomen = abdomen
        self.target_lengths = target_lengths

    def wall_radius(self, s, theta) -> np.ndarray:
        """Distance [m] from the centreline to the mucosa at arc length s [m], angle theta."""
        return self.wall.wall_radius(s, theta)

    def visual_mesh(self):
        """Closed wall at visual resolution (trimesh), normals into the lumen."""
        p = self.params
        return pouched_mesh(closed_tube(self, self._visual_stations(), p.visual_points_around),
                            self.diverticula, self.centerline)

    def _visual_stations(self):
        p = self.params
        return ring_stations(self, p.visual_axial_step,
                             p.visual_tolerance if p.visual_tolerance > 0 else None,
                             min(p.visual_min_step, p.visual_axial_step))

    def textured_visual_mesh(self):
        """`visual_mesh` with texture coordinates for the mucosa texture (`TexturedMesh`;
        the seam column and the caps' rims are duplicated, so it is not watertight)."""
        p = self.params
        m = p.mucosa
        return pouched_textured(textured_tube(self, self._visual_stations(),
                                              p.visual_points_around,
                                              m.texels_per_metre / m.texels_along,
                                              m.texels_per_metre / m.texels_around),
                                self.diverticula, self.centerline)

    def camera_mesh(self):
        """The textured wall at camera resolution (`TexturedMesh`), what capsule cameras
        render; same texture mapping as `textured_visual_mesh`."""
        p = self.params
        m = p.mucosa
        stations = ring_stations(self, p.camera_axial_step,
                                 p.camera_tolerance if p.camera_tolerance > 0 else None,
                                 min(p.camera_min_step, p.camera_axial_step))
        return pouched_textured(textured_tube(self, stations, p.camera_points_around,
                                              m.texels_per_metre / m.texels_along,
                                              m.texels_per_metre / m.texels_around),
                                self.diverticula, self.centerline)

    def texture_seed(self) -> list[int]:
        """Seed of the mucosa texture: the patient seed's own stream (the wall uses [seed, 1])."""
        return [self.params.seed, 2]

    def collision_meshes(self):
        """The wall at collision resolution in `collision_chunks` pieces (trimesh list)."""
        p = self.params
        stations = ring_stations(self, p.collision_axial_step,
                                 p.collision_tolerance if p.collision_tolerance > 0 else None,
                                 p.collision_min_step)
        return pouched_chunks(tube_chunks(self, stations, p.collision_points_around,
                                          p.collision_chunks), self.diverticula, self.centerline)


COURSE_FILE = "course.npz"
"""The solved course, kept with a procedural colon's files: solving it takes ~1 s, and a
process that cycles over more colons than it keeps in memory (a Gymnasium environment, a
benchmark's process per run) would solve it again for each build."""


def build_colon(params: ColonParams, course_file: Path | None = None) -> Colon:
    """Build the colon of patient `params.seed`. Pure and deterministic. With `course_file`
    (the `COURSE_FILE` of its cached files) the course is read from it when it is there
    instead of solved again: the same numbers, bit for bit."""
    course = None
    if params.population is not None:   # the population's patient of this seed
        params, course = resolve_population(params)
    if course_file is not None and course_file.exists():
        s, points, boundaries, targets = read_course(course_file)
    elif course is not None:
        s, points, boundaries, targets = course
    else:
        s, points, boundaries, targets = solve_course(params, np.random.default_rng(params.seed))
    segment = np.clip(np.searchsorted(boundaries, s, side="right") - 1, 0,
                      len(SEGMENT_NAMES) - 1)
    # The course is the distended patient's; a segment not fully distended (colon.lumen)
    # is narrower around the same centreline.
    radius = nominal_radius(s, boundaries, narrowed(params))
    # Tangents for the frame from finite differences; the Centerline refits them.
    tangents = np.gradient(points, s, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normals = rotation_minimising_frame(points, tangents, np.array([0.0, 0.0, 1.0]))
    centerline = Centerline(s, points, normals, radius, segment, SEGMENT_NAMES)
    wall = HaustralWall(params, centerline, np.random.default_rng([params.seed, 1]))
    colon = Colon(params, centerline, wall, Abdomen(params.abdomen), targets,
                  course=(s, points, boundaries))
    # Pouches in the wall (their meshes are cut for them); polyps are geometry of their own.
    colon.diverticula = tuple(place_diverticula(colon, drawn_lesions(params)))
    return colon


def write_course(colon: Colon, path: Path) -> None:
    """The solved course of `colon` (what `build_colon` reads back)."""
    names = list(colon.target_lengths)
    np.savez(path, s=colon.course[0], points=colon.course[1], boundaries=colon.course[2],
             target_names=np.array(names), target_lengths=np.array(
                 [colon.target_lengths[n] for n in names]))


def read_course(path: Path):
    """(s, points, boundaries, targets) as `solve_course` returned them."""
    with np.load(path) as data:
        targets = {str(n): float(v) for n, v in zip(data["target_names"],
                                                     data["target_lengths"])}
        return data["s"], data["points"], data["boundaries"], targets


def write_colon_assets(colon: Colon, directory: Path) -> ColonAssets:
    """Write every mesh, the centreline and the course of `colon` into `directory`."""
    write_course(colon, directory / COURSE_FILE)
    mucosa = colon.params.mucosa
    return write_asset_files(
        directory, colon.collision_meshes(), colon.textured_visual_mesh(),
        lambda path: write_mucosa_texture(path, mucosa, colon.texture_seed()), mucosa,
        colon.centerline, colon.abdomen.torso_mesh())


def procedural_colon_assets(params: ColonParams, cache_dir=None) -> ColonAssets:
    """Generated files of the colon for `params`, built once and cached.

    The files live in `<root>/<params_hash>/`, root = `cache_dir` if given, else
    `default_cache_root()`. They are written to a temporary directory and renamed into
    place, so concurrent processes never see a half-written set.
    """
    root = Path(cache_dir) if cache_dir is not None else default_cache_root()
    final = root / params_hash(shape_params(params))
    build_once(final, lambda tmp: write_colon_assets(build_colon(params), tmp))
    return asset_paths(final, len(sorted(final.glob("colon_collision_*.obj"))))
