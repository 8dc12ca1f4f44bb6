"""A colon's generated files: where they live, their cache key, and writing them once.

The procedural colon (anatomy/colon.py) and an imported one (anatomy/imported.py) write the
same set of files (`write_asset_files`) into a folder of the cache, built once and renamed
into place (`build_once`), keyed by their parameters and this package's source.

The cache lives in $CAPSULE_DRAKE_CACHE, else ~/.cache/capsule_drake (`cache_base`), checked
once per process before anything is built there:
- a value that names a file (or a path through one) is a mistake in the variable: refused
  with one line (`CacheError`);
- a folder that cannot be written (read-only, not permitted, a full disk) is not the user's
  input but the machine's state: the run goes on without the cache, its colon built in a
  temporary folder removed when the process ends, with one warning line saying so (a
  rebuilt colon costs seconds; refusing would stop every run on a machine whose home or
  shared cache is read-only).
"""

import atexit
import contextlib
import errno
import hashlib
import logging
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

CACHE_VARIABLE = "CAPSULE_DRAKE_CACHE"
"""The environment variable naming the cache folder."""

MIN_FREE_BYTES = 100 * 2**20
"""Room the cache needs to be used: a colon's files are 10-30 MB (procedural colons; an
imported mesh's are smaller), its camera windows and lesions' meshes add a few more."""

_log = logging.getLogger("capsule_drake.anatomy")


class CacheError(ValueError):
    """The cache cannot be used; the message is one line naming the folder (and the
    environment variable when it set the folder)."""


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
    """$CAPSULE_DRAKE_CACHE/colon if set, else ~/.cache/capsule_drake/colon (`cache_base`)."""
    return cache_base() / "colon"


_BASES: dict[str, Path] = {}


def cache_base() -> Path:
    """The cache folder: $CAPSULE_DRAKE_CACHE if set, else ~/.cache/capsule_drake, made and
    checked once per process (and per value of the variable).

    Raises:
        CacheError: the variable names a file, or a path through one (one line).

    A folder that cannot be written (read-only, not permitted, less than MIN_FREE_BYTES
    free) gives one warning and a temporary folder instead, removed when the process
    ends; the variable is set to it, so that the processes this one starts (the camera's
    renderer, the benchmark's workers) use it too."""
    value = os.environ.get(CACHE_VARIABLE, "")
    if value not in _BASES:
        _BASES[value] = _usable_base(value)
    return _BASES[value]


def _usable_base(value: str) -> Path:
    if value:
        base, named = Path(value).expanduser(), f"{CACHE_VARIABLE}={value}"
    else:
        try:
            base = Path.home() / ".cache" / "capsule_drake"
        except RuntimeError as e:  # no home folder
            return _temporary_base(f"the cache folder ~/.cache/capsule_drake", str(e))
        named = f"the cache folder {base} ({CACHE_VARIABLE} unset)"
    for folder in (base, *base.parents):
        if os.path.lexists(folder):
            if not folder.is_dir():
                kind = ("a file" if folder.is_file() else "not a folder" if folder.exists()
                        else "a broken link")
                where = f"it is {kind}" if folder == base else f"{folder} is {kind}"
                raise CacheError(f"{named}: cannot be a folder ({where}); point "
                                 f"{CACHE_VARIABLE} at a folder (or unset it for "
                                 "~/.cache/capsule_drake)")
            break
    try:
        (base / "colon").mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=base) as probe:
            probe.write(b"\0" * 4096)
            probe.flush()
            os.fsync(probe.fileno())
        free = shutil.disk_usage(base).free
        if free < MIN_FREE_BYTES:
            raise OSError(errno.ENOSPC, f"{free / 2**20:.0f} MB free, less than the "
                                        f"{MIN_FREE_BYTES / 2**20:.0f} MB a colon's files need")
    except OSError as e:
        return _temporary_base(named, e.strerror or str(e))
    return base


def _temporary_base(named: str, reason: str) -> Path:
    """A temporary cache folder for this process and its children (one warning)."""
    try:
        base = Path(tempfile.mkdtemp(prefix="capsule_drake-cache-"))
        (base / "colon").mkdir()
    except OSError as e:
        raise CacheError(f"{named}: cannot be written ({reason}), nor can a temporary "
                         f"folder ({e.strerror or e}); free some room, or point "
                         f"{CACHE_VARIABLE} at a folder that can be written") from None
    atexit.register(shutil.rmtree, base, ignore_errors=True)
    os.environ[CACHE_VARIABLE] = str(base)
    _BASES[str(base)] = base
    _log.warning(f"warning: {named}: cannot be written ({reason}); running without the "
                 f"cache: this run's colon files go to a temporary folder, removed when it "
                 f"ends (point {CACHE_VARIABLE} at a folder that can be written to keep "
                 "them)")
    return base


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


# A write into the cache that fails for want of room or permission: the cache's state, said
# in one line naming it (CacheError), not a defect.
_NO_WRITE = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


@contextlib.contextmanager
def _cache_writes(folder: Path):
    try:
        yield
    except OSError as e:
        if e.errno not in _NO_WRITE:
            raise
        raise CacheError(f"the colon cache {folder}: could not write a colon's files there "
                         f"({e.strerror or e}); free some room, or point {CACHE_VARIABLE} "
                         "at a folder that can be written") from None


def write_atomic(path: Path, write) -> None:
    """Runs write(temporary path) beside `path` and renames the file into place, so that
    concurrent processes never see it half written. Raises CacheError (one line) when the
    cache has no room or cannot be written."""
    with _cache_writes(path.parent):
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        with _cache_writes(path.parent):
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
    with _cache_writes(final.parent):
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=final.parent))
    try:
        with _cache_writes(final.parent):
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
