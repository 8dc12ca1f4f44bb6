"""A colon's generated files: where they live, their cache key, and writing them once.

The procedural colon (anatomy/colon.py) and an imported one (anatomy/imported.py) write the
same set of files (`write_asset_files`) into a folder of the cache, built once and renamed
into place (`build_once`), keyed by their parameters and this package's source.
"""

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed

from .mesh import SKIN_MTL, mucosa_mtl, write_obj, write_textured_obj

GEOMETRY_VERSION = 1
"""Bump whenever code changes the generated geometry: it invalidates cached assets."""

MUCOSA_TEXTURE = "colon_mucosa.png"
"""File name of the mucosa texture, next to the visual OBJ (its MTL refers to it)."""


@dataclass
class ColonAssets:
    """Files of one generated colon (all in one cache directory)."""

    visual_obj: Path
    collision_objs: list[Path]
    centerline_npz: Path
    torso_obj: Path


def source_digest() -> str:
    """Hash of this package's source: a code change must never reuse stale cached meshes."""
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def params_hash(params) -> str:
    """Cache key: hash of the YAML dump of the params, GEOMETRY_VERSION and the source."""
    text = f"v{GEOMETRY_VERSION}\n{source_digest()}\n" + yaml_dump_typed(params)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def default_cache_root() -> Path:
    """$CAPSULE_DRAKE_CACHE/colon if set, else ~/.cache/capsule_drake/colon."""
    env = os.environ.get("CAPSULE_DRAKE_CACHE")
    base = Path(env) if env else Path.home() / ".cache" / "capsule_drake"
    return base / "colon"


def asset_paths(directory: Path, chunks: int) -> ColonAssets:
    return ColonAssets(
        visual_obj=directory / "colon_visual.obj",
        collision_objs=[directory / f"colon_collision_{k:02d}.obj" for k in range(chunks)],
        centerline_npz=directory / "centerline.npz",
        torso_obj=directory / "torso.obj")


def write_asset_files(directory: Path, chunks, visual, write_texture, mucosa, centerline,
                      torso) -> ColonAssets:
    """A colon's files in `directory`: the visual OBJ (`visual`, a TexturedMesh) with its
    material and texture (`write_texture(path)` writes the image), the collision chunks
    (trimesh list), the centreline and the torso (drawn around the colon)."""
    directory.mkdir(parents=True, exist_ok=True)
    assets = asset_paths(directory, len(chunks))
    write_texture(directory / MUCOSA_TEXTURE)
    (directory / "colon_visual.mtl").write_text(
        mucosa_mtl(MUCOSA_TEXTURE, mucosa.specular, mucosa.shininess))
    write_textured_obj(assets.visual_obj, visual, material=("colon_visual.mtl", "mucosa"))
    for path, mesh in zip(assets.collision_objs, chunks):
        write_obj(path, mesh)
    centerline.save(assets.centerline_npz)
    (directory / "torso.mtl").write_text(SKIN_MTL)
    write_obj(assets.torso_obj, torso, normals=True, material=("torso.mtl", "skin"))
    return assets


def write_atomic(path: Path, write) -> None:
    """Runs write(temporary path) beside `path` and renames the file into place, so that
    concurrent processes never see it half written."""
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def build_once(final: Path, write) -> None:
    """Unless folder `final` is complete (it has centerline.npz), runs write(folder) into a
    temporary folder beside it and renames that into place, so concurrent processes never
    see a half-written set."""
    if (final / "centerline.npz").exists():
        return
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=final.parent))
    try:
        write(tmp)
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "centerline.npz").exists():
                raise
            # Another process won the race; its files are identical.
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
