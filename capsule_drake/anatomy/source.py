"""One place that loads a scenario's colon, whatever its source, behind one cache.

`load_colon(params)` returns (colon, assets) for `params.source`: !Procedural or
!Population (generated from the seed, anatomy/colon.py), !ExVivo (the shipped porcine
segment, generated and imported) or !Imported (a user's mesh or import folder,
anatomy/imported.py). The colon answers the
same queries in every case (`TubeColon`); its files (meshes, texture, centreline) are cached
on disk (anatomy/cache.py) and the loaded colon in memory, once per process for equal
parameters. `colon_wall_pieces` gives the convex wall pieces of the fast contact model.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from pathlib import Path

import cv2
import numpy as np
import trimesh
from pydrake.common.yaml import yaml_dump_typed

from .cache import CacheError, ColonAssets, write_atomic
from .colon import COURSE_FILE, build_colon, procedural_colon_assets
from .fluid import fluid_pools, surface_mesh
from .imported import imported_colon_assets
from .diverticula import PlacedDiverticulum
from .lesion_geometry import POINTS_AROUND, PlacedPolyp, place_polyps, polyp_rgba
from .lesion_texture import polyp_texture, textured_revolution
from .lesions import drawn_lesions
from .lumen_state import BUBBLE_RADIUS, drawn_lumen, geometry_params
from .mesh import mucosa_mtl, write_obj, write_textured_obj
from .params import ColonParams
from .pieces import wall_pieces

_LOADED: dict[str, tuple] = {}
_PIECES: dict[tuple, list] = {}
_KEEP = 4  # colons kept in memory (a benchmark process runs one colon after another)


class ColonSourceError(ValueError):
    """The colon's source cannot be loaded; the message is one line."""


def load_colon(params: ColonParams, cache_dir=None) -> tuple:
    """(colon, ColonAssets) of `params`, built or imported once and cached. Raises
    ColonSourceError (one line) when an imported source cannot be read. The lumen's fluid
    and bubbles are not part of the colon (`fluid_scene`): colons that differ only in them
    are one."""
    params = geometry_params(params)
    key = yaml_dump_typed(params) + f"\n{cache_dir}"
    if key not in _LOADED:
        if len(_LOADED) >= _KEEP:
            _LOADED.pop(next(iter(_LOADED)))
        if params.procedural:
            assets = procedural_colon_assets(params, cache_dir)
            course = assets.centerline_npz.parent / COURSE_FILE
            _LOADED[key] = (build_colon(params, course), assets)
        else:
            try:
                _LOADED[key] = imported_colon_assets(params, cache_dir)
            except CacheError:  # the cache's, not the source's: said as it is
                raise
            except (ValueError, FileNotFoundError) as e:  # MeshImportError is a ValueError
                text = str(e).strip()
                first = text.splitlines()[0] if text else type(e).__name__
                raise ColonSourceError(f"colon.source: {first}") from None
    return _LOADED[key]


def colon_assets(params: ColonParams, cache_dir=None) -> ColonAssets:
    """The files of the colon of `params` (see `load_colon`)."""
    return load_colon(params, cache_dir)[1]


def colon_wall_pieces(params: ColonParams, axial_length: float, max_chord_depth: float):
    """The convex pieces of the procedural colon's wall (anatomy/pieces.py), built once per
    process for equal parameters."""
    params = geometry_params(params)
    key = (yaml_dump_typed(params), axial_length, max_chord_depth)
    if key not in _PIECES:
        _PIECES.clear()
        _PIECES[key] = wall_pieces(load_colon(params)[0], axial_length=axial_length,
                                   max_chord_depth=max_chord_depth)
    return _PIECES[key]


@dataclasses.dataclass
class FluidScene:
    """What the fluid of a colon adds to the scene."""

    pools: list                 # anatomy/fluid.py FluidPool, by arc length
    surface_obj: Path | None    # the liquid's surfaces, one OBJ; None without fluid
    bubbles_obj: Path | None = None   # the bubbles on it, one OBJ; None without any


@dataclasses.dataclass
class LesionScene:
    """What the lesions of a colon add to the scene: the polyps on its wall, each with its
    mesh's OBJ (world coordinates, written beside the colon's cached files)."""

    polyps: list[PlacedPolyp]
    objs: list[Path]
    # Each polyp's textured surface (anatomy/lesion_texture.py): an OBJ with its material
    # and texture, what cameras render.
    surface_objs: list[Path] = dataclasses.field(default_factory=list)
    # The pouches cut into the wall (anatomy/diverticula.py) and each one's sac as an OBJ
    # (the colon's meshes already have the hole and its collar).
    diverticula: list[PlacedDiverticulum] = dataclasses.field(default_factory=list)
    sac_objs: list[Path] = dataclasses.field(default_factory=list)

    @property
    def lesions(self) -> list:
        """Polyps and diverticula, by index."""
        return sorted(self.polyps + self.diverticula, key=lambda lesion: lesion.index)


_log = logging.getLogger("capsule_drake.anatomy")
_SCENES: dict[str, FluidScene] = {}
_LESION_SCENES: dict[str, LesionScene] = {}


def _fluid_scene(key: str, params: ColonParams, folder: str) -> FluidScene:
    state = drawn_lumen(params)
    if state is None or state.fluid_ml <= 0.0:
        return FluidScene([], None)
    colon = load_colon(params)[0]
    pools = fluid_pools(colon, state.fluid_ml * 1e-6)
    placed = 1e6 * sum(pool.volume for pool in pools)
    if placed < 0.99 * state.fluid_ml:
        _log.warning(f"colon.lumen.fluid_ml: this colon's basins hold {placed:.1f} ml of the "
                     f"{state.fluid_ml:.1f} ml asked for; the rest is not placed (it would "
                     "run out of the colon)")
    meshes = [m for m in (surface_mesh(colon, pool) for pool in pools) if m is not None]
    if not meshes:
        return FluidScene(pools, None)
    stem = f"fluid_{hashlib.sha256(key.encode()).hexdigest()[:16]}"
    surface = trimesh.util.concatenate(meshes)
    bubbles = _bubbles(surface, state.bubbles, np.random.default_rng([params.seed, 12]))
    paths = []
    for name, mesh in ((f"{stem}.obj", surface), (f"{stem}_bubbles.obj", bubbles)):
        path = Path(folder) / name
        if mesh is not None and not path.exists():
            write_atomic(path, lambda tmp, m=mesh: write_obj(tmp, m, normals=True))
        paths.append(path if mesh is not None else None)
    return FluidScene(pools, *paths)


def _bubbles(surface, count: int, rng) -> trimesh.Trimesh | None:
    """`count` spheres centred on the liquid's `surface` (half above it): two in three at
    its edge against the wall (where bubbles gather), the rest anywhere on it; radii
    log-uniform in BUBBLE_RADIUS."""
    if count <= 0:
        return None
    edge = surface.vertices   # the chords' ends lie on the wall
    spheres = []
    for k in range(count):
        if k % 3 < 2:
            centre = edge[rng.integers(len(edge))]
        else:
            face = surface.vertices[surface.faces[rng.integers(len(surface.faces))]]
            w = rng.dirichlet(np.ones(3))
            centre = w @ face
        radius = float(np.exp(rng.uniform(*np.log(BUBBLE_RADIUS))))
        sphere = trimesh.creation.icosphere(subdivisions=1, radius=radius)
        sphere.apply_translation(centre)
        spheres.append(sphere)
    return trimesh.util.concatenate(spheres)


def fluid_scene(params: ColonParams) -> FluidScene:
    """The fluid pools of the colon of `params` and their surface's OBJ (written beside the
    colon's cached files), once per process for equal parameters."""
    folder = colon_assets(params).visual_obj.parent
    key = yaml_dump_typed(params)
    if key not in _SCENES:
        if len(_SCENES) >= 8:
            _SCENES.pop(next(iter(_SCENES)))
        _SCENES[key] = _fluid_scene(key, params, str(folder))
    return _SCENES[key]


def _polyp_surface(folder: Path, stem: str, polyp: PlacedPolyp, params: ColonParams) -> Path:
    """The polyp's textured OBJ, its material and its texture (anatomy/lesion_texture.py),
    written once beside the colon's files; returns the OBJ's path."""
    obj = folder / f"{stem}_surface.obj"
    if obj.exists():
        return obj
    mucosa = params.mucosa
    diameter = 1e-3 * polyp.lesion.size_mm
    image, _ = polyp_texture(polyp_rgba(mucosa.base_color), np.pi * diameter,
                             polyp.height + 0.5 * diameter, [params.seed, 23, 2, polyp.index])
    png, mtl = f"{stem}_surface.png", f"{stem}_surface.mtl"

    def write_png(tmp):
        if not cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write the polyp texture {png}")

    write_atomic(folder / png, write_png)
    write_atomic(folder / mtl, lambda tmp: Path(tmp).write_text(
        mucosa_mtl(png, mucosa.specular, mucosa.shininess)))
    mesh = textured_revolution(polyp.mesh, POINTS_AROUND)
    write_atomic(obj, lambda tmp: write_textured_obj(tmp, mesh, (mtl, "mucosa")))
    return obj


def lesion_scene(params: ColonParams) -> LesionScene:
    """The polyps of the colon of `params` (anatomy/lesions.py, anatomy/lesion_geometry.py)
    placed on its wall, and their OBJs, once per process for equal parameters; empty when
    `params.lesions` is null."""
    if params.lesions is None:
        return LesionScene([], [])
    key = yaml_dump_typed(params)
    if key not in _LESION_SCENES:
        if len(_LESION_SCENES) >= 8:
            _LESION_SCENES.pop(next(iter(_LESION_SCENES)))
        colon = load_colon(params)[0]
        lesions = drawn_lesions(params)
        if not params.procedural and any(not lesion.polyp for lesion in lesions):
            _log.warning(f"colon.lesions: the diverticula drawn for this patient are not "
                         f"cut into colon.source {params.source_name()} (only a procedural "
                         "or population colon's wall is); its polyps are placed")
        polyps = place_polyps(colon, lesions)
        # The colon's pouches, in the order of the patient's list (their indices there).
        pouch_index = [k for k, lesion in enumerate(lesions) if not lesion.polyp]
        pouches = [dataclasses.replace(pouch, index=pouch_index[pouch.index])
                   for pouch in colon.diverticula]
        folder = colon_assets(params).visual_obj.parent
        stem = f"lesion_{hashlib.sha256(key.encode()).hexdigest()[:16]}"
        objs, sacs = [], []
        for lesion, mesh, out in ([(p, p.mesh, objs) for p in polyps]
                                  + [(p, p.sac, sacs) for p in pouches]):
            path = folder / f"{stem}_{lesion.index:03d}.obj"
            if not path.exists():
                write_atomic(path, lambda tmp, m=mesh: write_obj(tmp, m, normals=True))
            out.append(path)
        surfaces = [_polyp_surface(folder, f"{stem}_{p.index:03d}", p, params)
                    for p in polyps]
        _LESION_SCENES[key] = LesionScene(polyps, objs, surfaces, pouches, sacs)
    return _LESION_SCENES[key]
