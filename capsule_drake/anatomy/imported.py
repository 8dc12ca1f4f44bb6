"""A colon from a mesh: the import pipeline, its files, and the colon the station runs on.

`import_colon_mesh(path)` loads a user's mesh, checks and repairs it (anatomy/importer.py),
extracts its centreline (anatomy/centerline_extraction.py), starts the arc length at the
narrower end (the anus: the rectum is narrower than the cecum) and tabulates the wall's
distance from the centreline around it. `write_import` stores the result in a folder
(`capsule-sim import-colon` writes one); `ImportedColon.load(folder)` reads it back.

`ImportedColon` answers what the procedural `Colon` answers (anatomy/colon.py
`TubeColon`), so metrics, lumen truth, camera windows and the EPM's path work on it
unchanged:
- wall_radius(s, theta): the tabulated distance from the centreline to the lumen's wall in
  the plane normal to it, every `TABLE_STEP` of arc length and `TABLE_AROUND` angles
  (sections of the mesh), interpolated;
- the collision chunks: the wall's faces split along the arc length;
- the render mesh: the wall with its own texture if the file had one, else the procedural
  mucosa texture mapped by (theta, s);
- `abdomen`: there is no abdomen around a mesh, so a flat `FlatSkin` a set height above its
  highest point is what the EPM keeps its clearance from.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh
from pydrake.common.yaml import yaml_dump_typed
from scipy.interpolate import RegularGridInterpolator

from .centerline import Centerline, rotation_minimising_frame
from .centerline_extraction import MeshSections, extract_centerline, section_loop
from .cache import GEOMETRY_VERSION, asset_paths, build_once, default_cache_root, source_digest, write_asset_files
from .colon import TubeColon
from .ex_vivo import TRAY_RGBA, tray_boxes, tray_mesh, write_segment
from . import importer
from .importer import (MeshImportError, RepairReport, _texture_of, check_colon_mesh,
                       geometry_of, load_colon_mesh, repair_colon_mesh)
from .mesh import TexturedMesh
from .params import ExVivo, Imported, MucosaParams
from .texture import mucosa_texture
from .tube_check import NotATubeError, check_one_piece, check_open_ends, check_tube

TABLE_STEP = 0.002
"""Arc-length step [m] of the wall-radius table."""
TABLE_AROUND = 64
"""Angles around the centreline in the wall-radius table."""
DEFAULT_MAX_FACES = 150_000
"""Triangle budget of an imported wall: a software camera render costs per triangle."""
NOTE_FACES = 100_000
"""A mesh imported on first use in a run (no progress bar there) with more triangles than
this says each stage of its import on stderr as it starts: such an import takes from half a
minute (100,000 triangles) to minutes (millions) on a 2-core machine."""


class FlatSkin:
    """The surface the EPM keeps clear of above an imported colon: the plane z = `height`
    over the mesh's footprint, drawn as a thin translucent slab (or as `display_mesh`)."""

    def __init__(self, height: float, bounds: np.ndarray, display_mesh=None,
                 display_rgba=None):
        self.height = float(height)
        self.bounds = np.asarray(bounds, dtype=float)  # [[xmin, ymin], [xmax, ymax]]
        self._display = display_mesh
        self.display_rgba = display_rgba

    def skin_height(self, x, y) -> np.ndarray:
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, self.height)

    def depth(self, points) -> np.ndarray:
        points = np.atleast_2d(points)
        return self.height - points[:, 2]

    def torso_mesh(self) -> trimesh.Trimesh:
        if self._display is not None:
            return self._display
        (x0, y0), (x1, y1) = self.bounds
        margin = 0.05
        box = trimesh.creation.box(extents=[x1 - x0 + 2 * margin, y1 - y0 + 2 * margin, 0.002])
        box.apply_translation([(x0 + x1) / 2, (y0 + y1) / 2, self.height - 0.001])
        return box


@dataclasses.dataclass
class ImportedWall:
    """The result of `import_colon_mesh`."""

    mesh: trimesh.Trimesh  # repaired, normals toward the lumen, texture kept if any
    report: RepairReport
    centerline: Centerline
    table_s: np.ndarray  # (S,) arc lengths of the wall-radius table [m]
    table_theta: np.ndarray  # (A,) angles [rad]
    table_radius: np.ndarray  # (S, A) distance from the centreline to the wall [m]
    source: str = ""
    scale: float = 1.0


def import_colon_mesh(path, scale: float = 1.0, max_faces: int | None = DEFAULT_MAX_FACES,
                      reverse: bool = False, progress=None,
                      notes_over: int | None = None) -> ImportedWall:
    """Load, check, repair and measure a user's colon mesh. Raises MeshImportError (one line)
    for a file that cannot become a colon (more than importer.MAX_IMPORT_FACES triangles
    among them), NotATubeError (a MeshImportError) for a mesh that is not one tube
    (anatomy/tube_check.py: in pieces, a triangle soup, more than two open ends, an open
    sheet, a closed blob, a branch). `progress(text)`, if given, hears each stage; with
    `notes_over`, a mesh of more triangles than that also says each stage on stderr."""
    say = progress or (lambda text: None)
    noted = False
    if notes_over is not None:  # the triangles the file states, if it does: before reading
        stated = _stated_faces(path)
        if stated is not None and notes_over < stated <= importer.MAX_IMPORT_FACES:
            say, noted = _noting(say, path, stated), True
    say("reading")
    mesh = load_colon_mesh(path)
    if notes_over is not None and not noted and len(mesh.faces) > notes_over:
        say = _noting(say, path, len(mesh.faces))
    if scale != 1.0:
        mesh.apply_scale(scale)
    check_colon_mesh(mesh, str(path))
    try:
        check_one_piece(mesh.vertices, mesh.faces)
    except NotATubeError as e:
        raise NotATubeError(f"{path}: {e}") from None
    say("repairing")
    mesh, report = repair_colon_mesh(mesh, max_faces=max_faces, progress=say)
    geometry = geometry_of(mesh)
    try:
        check_open_ends(report.open_end_perimeters)
        s, points, radius = extract_centerline(
            geometry, progress=lambda k, n: say(f"centreline, pass {k + 1} of {n}"))
        check_tube(geometry, s, points, radius)
    except NotATubeError as e:
        raise NotATubeError(f"{path}: {e}") from None
    except (ValueError, IndexError, np.linalg.LinAlgError) as e:
        # No line could be followed through it (the fits had too few sections, or none
        # closed around the line): what is left of a sheet or a scrap is not a tube.
        text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise NotATubeError(f"{path}: not a tube: no centreline could be followed through "
                            f"it ({text})") from None
    # s = 0 at the narrower end (the anus), unless asked otherwise.
    ends = max(2, int(np.searchsorted(s, min(0.05, 0.25 * s[-1]))))
    if (np.median(radius[:ends]) > np.median(radius[-ends:])) != reverse:
        points, radius = points[::-1], radius[::-1]
        s = s[-1] - s[::-1]
    centerline = _centerline(s, points, radius)
    say("wall table")
    table_s, theta, table = wall_radius_table(geometry, centerline)
    return ImportedWall(mesh, report, centerline, table_s, theta, table, str(path), scale)


def _stated_faces(path) -> int | None:
    try:
        return importer.count_faces(Path(path)) if Path(path).is_file() else None
    except OSError:
        return None  # said by the read


def _noting(say, path, faces: int):
    """`say`, its texts also lines on stderr naming the import, with the seconds since: each
    new stage (the text's words before a comma), and a stage's steps 10 s apart."""
    start = time.perf_counter()
    head = f"importing {path} ({faces:,} triangles; cached after this first use)"
    last = {"stage": None, "time": -np.inf}

    def noted(text):
        now = time.perf_counter()
        stage = text.split(",")[0]
        if stage != last["stage"] or now - last["time"] >= 10.0:
            print(f"{head}: {text} ({now - start:.0f} s)", file=sys.stderr, flush=True)
            last.update(stage=stage, time=now)
        say(text)
    return noted


def _centerline(s, points, radius) -> Centerline:
    tangents = np.gradient(points, s, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    helper = np.array([0.0, 0.0, 1.0]) if abs(tangents[0, 2]) < 0.9 else np.array([1.0, 0, 0])
    normals = rotation_minimising_frame(points, tangents, helper)
    return Centerline(s, points, normals, radius, np.zeros(len(s), dtype=int), ["imported"])


def wall_radius_table(mesh: trimesh.Trimesh, centerline: Centerline, step: float = TABLE_STEP,
                      around: int = TABLE_AROUND):
    """(s (S,), theta (A,), radius (S, A)): the distance from the centreline to the lumen's
    wall in the plane normal to it, from the section's loop around the centreline (its
    polar radius interpolated at each angle, theta from the frame's normal toward its
    binormal). Stations where the plane cuts no loop around the lumen (beyond an open,
    ragged end) take the nearest station's values."""
    length = centerline.length
    s = np.linspace(0.0, length, max(2, int(np.ceil(length / step)) + 1))
    theta = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    table = np.full((len(s), around), np.nan)
    t, n, b = centerline.frame_at(s)
    origins = centerline.point_at(s)
    sections = MeshSections(mesh)
    for k in range(len(s)):
        cut = section_loop(mesh, origins[k], t[k], sections)
        if cut is None:
            continue
        d = cut[0] - origins[k]
        x, y = d @ n[k], d @ b[k]
        angle = np.mod(np.arctan2(y, x), 2.0 * np.pi)
        rho = np.hypot(x, y)
        if np.linalg.norm(cut[1] - origins[k]) > 0.5 * np.sqrt(cut[2] / np.pi):
            continue  # a loop that is not around this station (another stretch of tube)
        order = np.argsort(angle)
        table[k] = np.interp(theta, angle[order], rho[order], period=2.0 * np.pi)
    good = np.flatnonzero(~np.isnan(table[:, 0]))
    if len(good) == 0:
        raise ValueError("no section of the mesh encloses its centreline")
    nearest = good[np.clip(np.searchsorted(good, np.arange(len(s))), 0, len(good) - 1)]
    before = good[np.clip(np.searchsorted(good, np.arange(len(s))) - 1, 0, len(good) - 1)]
    use = np.where(np.abs(before - np.arange(len(s))) < np.abs(nearest - np.arange(len(s))),
                   before, nearest)
    table = table[use]
    return s, theta, table


def write_import(wall: ImportedWall, out) -> dict:
    """Writes the import into folder `out`: wall.obj (with its material and texture if it
    has one), centerline.npz, wall_radius.npz and import.json (a summary). Returns the
    summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    wall.mesh.export(out / "wall.obj")
    wall.centerline.save(out / "centerline.npz")
    np.savez(out / "wall_radius.npz", s=wall.table_s, theta=wall.table_theta,
             radius=wall.table_radius)
    radius = wall.centerline.radius
    summary = {"source": wall.source, "scale": wall.scale, "faces": int(len(wall.mesh.faces)),
               "vertices": int(len(wall.mesh.vertices)),
               "textured": _texture_of(wall.mesh) is not None,
               "repairs": wall.report.lines(),
               "centreline_length_m": round(wall.centerline.length, 4),
               "radius_m": {"min": round(float(np.min(radius)), 4),
                            "median": round(float(np.median(radius)), 4),
                            "max": round(float(np.max(radius)), 4)}}
    (out / "import.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def _file_image(mesh: trimesh.Trimesh):
    """The mesh's own texture image as (H, W, 3) uint8 RGB, or None."""
    texture = _texture_of(mesh)
    if texture is None:
        return None
    image = getattr(texture[1], "image", None)
    if image is None:
        image = getattr(texture[1], "baseColorTexture", None)
    return None if image is None else np.asarray(image.convert("RGB"))


class ImportedColon(TubeColon):
    """A colon read from an import folder (`write_import`).

    Attributes:
        centerline: from the narrower end (s = 0) to the other, one segment "imported".
        mesh: the wall (trimesh; its texture, if any, in mesh.visual).
        abdomen: the `FlatSkin` `skin_above` (m) over the wall's highest point.
        collision_boxes: (extents, centre) boxes around the colon that the capsule can
            touch (the ex vivo segment's tray: a capsule that leaves the tissue by an open
            end lands in it).
    """

    def __init__(self, mesh: trimesh.Trimesh, centerline: Centerline, table_s, table_theta,
                 table_radius, skin_above: float = 0.02, display_mesh=None,
                 display_rgba=None, mucosa: MucosaParams | None = None, seed: int = 0):
        self.mesh = mesh
        self.mucosa = mucosa or MucosaParams()
        self.seed = seed
        self.geometry = geometry_of(mesh)
        self.centerline = centerline
        theta = np.concatenate([table_theta, [2.0 * np.pi]])
        radius = np.concatenate([table_radius, table_radius[:, :1]], axis=1)
        self._table = RegularGridInterpolator((table_s, theta), radius)
        self._s_max = float(table_s[-1])
        lo, hi = self.geometry.bounds
        self.abdomen = FlatSkin(hi[2] + skin_above, [lo[:2], hi[:2]], display_mesh,
                                display_rgba)

    @classmethod
    def load(cls, folder, skin_above: float = 0.02, display_mesh=None, display_rgba=None,
             mucosa: MucosaParams | None = None, seed: int = 0):
        folder = Path(folder)
        for name in ("wall.obj", "centerline.npz", "wall_radius.npz"):
            if not (folder / name).is_file():
                raise FileNotFoundError(f"{folder}: no {name} (not a capsule-sim "
                                        "import-colon folder)")
        mesh = trimesh.load(str(folder / "wall.obj"), process=False, force="mesh")
        with np.load(folder / "wall_radius.npz") as table:
            s, theta, radius = table["s"], table["theta"], table["radius"]
        return cls(mesh, Centerline.load(folder / "centerline.npz"), s, theta, radius,
                   skin_above, display_mesh, display_rgba, mucosa, seed)

    def wall_radius(self, s, theta) -> np.ndarray:
        s, theta = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(theta, dtype=float))
        query = np.stack([np.clip(s, 0.0, self._s_max), np.mod(theta, 2.0 * np.pi)], axis=-1)
        return self._table(query.reshape(-1, 2)).reshape(s.shape)

    def visual_mesh(self) -> trimesh.Trimesh:
        return self.geometry

    def camera_mesh(self) -> TexturedMesh:
        """The wall with texture coordinates: the file's own if it had a texture, else
        u = theta / 2 pi around and v = s / (tiles x the texture's period) along, for the
        procedural mucosa texture stacked `tiles` times (texture coordinates stay in
        [0, 1]: Drake's VTK engine does not repeat a texture). Faces across the seam
        theta = 0 get their own copies of the seam's vertices at u + 1."""
        mesh = self.mesh
        vertices = np.asarray(mesh.vertices, dtype=float)
        faces = np.asarray(mesh.faces)
        s, _, theta = self.centerline.closest(vertices)
        if _file_image(mesh) is not None:
            uv = np.asarray(mesh.visual.uv, dtype=float)
        else:
            period = self.mucosa.texels_along / self.mucosa.texels_per_metre
            tiles = self.texture_tiles()
            uv = np.column_stack([np.mod(theta, 2 * np.pi) / (2 * np.pi),
                                  s / (tiles * period)])
            wraps = np.ptp(uv[faces, 0], axis=1) > 0.5
            low = (uv[faces, 0] < 0.5) & wraps[:, None]
            copies = np.unique(faces[low])
            index = np.full(len(vertices), -1)
            index[copies] = len(vertices) + np.arange(len(copies))
            faces = faces.copy()
            faces[low] = index[faces[low]]
            vertices = np.concatenate([vertices, vertices[copies]])
            uv = np.concatenate([uv, uv[copies] + [1.0, 0.0]])
            s = np.concatenate([s, s[copies]])
        normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
        return TexturedMesh(vertices, np.asarray(normals), uv, faces, s)

    def texture_tiles(self) -> int:
        """How many periods of the procedural texture cover the wall's length."""
        m = self.mucosa
        return max(1, int(np.ceil(self.centerline.length * m.texels_per_metre
                                  / m.texels_along)))

    def texture_image(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB: the file's texture, or the procedural mucosa texture
        stacked `texture_tiles()` times along (the mapping of `camera_mesh`)."""
        image = _file_image(self.mesh)
        if image is not None:
            return image
        rgb = mucosa_texture(self.mucosa, [self.seed, 2]).rgb
        return np.concatenate([rgb] * self.texture_tiles(), axis=0)

    def collision_meshes(self, chunks: int) -> list[trimesh.Trimesh]:
        """The wall's faces in `chunks` pieces along the arc length (by face centre)."""
        geometry = self.geometry
        s = self.centerline.closest(geometry.triangles_center)[0]
        edges = np.linspace(0.0, self.centerline.length, chunks + 1)
        which = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, chunks - 1)
        out = []
        for k in range(chunks):
            faces = np.asarray(geometry.faces)[which == k]
            if len(faces):
                piece = trimesh.Trimesh(geometry.vertices, faces, process=False)
                piece.remove_unreferenced_vertices()
                out.append(piece)
        return out


# --- Imported colons in scenarios: the `colon.source` field -------------------------------

def _digest(params, files) -> str:
    digest = hashlib.sha256(f"imported v{GEOMETRY_VERSION}\n{source_digest()}\n".encode())
    digest.update(yaml_dump_typed(params.source).encode())
    digest.update(f"{type(params.source).__name__} {params.collision_chunks}".encode())
    digest.update(yaml_dump_typed(params.mucosa).encode())
    if isinstance(params.source, ExVivo):
        digest.update(f"ex_vivo seed {params.seed}".encode())
    for path in files:
        digest.update(Path(path).name.encode())
        digest.update(Path(path).read_bytes())
    return "imported-" + digest.hexdigest()[:16]


def _source_files(source: Path) -> list[Path]:
    """The files an import depends on: a folder's import files, or the mesh file and any
    material and texture files beside it with the same stem."""
    if source.is_dir():
        files = [source / name for name in ("wall.obj", "centerline.npz", "wall_radius.npz")]
        for path in files:
            if not path.is_file():
                raise FileNotFoundError(f"{source}: no {path.name} (not a folder written by "
                                        "capsule-sim import-colon)")
        return files
    siblings = sorted(p for p in source.parent.glob(source.stem + "*") if p.is_file())
    return [source] + [p for p in siblings if p != source]


def imported_colon_assets(params, cache_dir=None):
    """(ImportedColon, ColonAssets) for an !Imported `params.source`: imported (or, for
    !ExVivo, generated and imported) once, its files cached like the procedural colon's
    (written to a temporary folder and renamed into place)."""
    root = Path(cache_dir) if cache_dir is not None else default_cache_root()
    if isinstance(params.source, ExVivo):
        files = []
    else:
        files = _source_files(Path(params.source.path))
    try:
        final = root / _digest(params, files)
    except OSError as e:  # a file the user may not read: theirs to fix, in one line
        raise MeshImportError(f"{e.filename or params.source.path}: cannot be read "
                              f"({e.strerror or e})") from None
    build_once(final, lambda tmp: _build_imported(params, tmp))
    chunks = len(sorted(final.glob("colon_collision_*.obj")))
    return _load_imported(params, final), asset_paths(final, chunks)


def _import_folder(params, directory: Path) -> Path:
    if isinstance(params.source, Imported) and Path(params.source.path).is_dir():
        return Path(params.source.path)
    return directory / "import"


def _load_imported(params, directory: Path) -> ImportedColon:
    display = rgba = None
    boxes = ()
    if isinstance(params.source, ExVivo):
        display, rgba, boxes = tray_mesh(), TRAY_RGBA, tray_boxes()
    colon = ImportedColon.load(_import_folder(params, directory), params.source.skin_above,
                               display, rgba, mucosa=params.mucosa, seed=params.seed)
    colon.collision_boxes = boxes
    return colon


def _build_imported(params, directory: Path) -> None:
    folder = _import_folder(params, directory)
    source = params.source
    if not (isinstance(source, Imported) and folder == Path(source.path)):
        if isinstance(source, ExVivo):
            mesh_path = write_segment(directory / "reconstruction", params.seed, params.mucosa)
        else:
            mesh_path = Path(source.path)
        scale = source.scale if isinstance(source, Imported) else 1.0
        write_import(import_colon_mesh(mesh_path, scale, source.max_faces, source.reverse,
                                       notes_over=NOTE_FACES), folder)
    colon = _load_imported(params, directory)
    image = colon.texture_image()

    def write_texture(path):
        if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {path}")

    write_asset_files(directory, colon.collision_meshes(params.collision_chunks),
                      colon.camera_mesh(), write_texture, params.mucosa, colon.centerline,
                      colon.abdomen.torso_mesh())
