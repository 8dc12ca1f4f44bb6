"""What the colon import refuses before it spends minutes, and how it reads what it accepts:
a picture given for a mesh is named for what it is (whatever the packages trimesh finds
installed), an OBJ in Latin-1 is read, a triangle soup (no connected wall) is refused before
the repairs, a mesh beyond what the import can handle is refused with its limit, and a long
import says what it is doing."""

import sys
import types

import cv2
import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy.importer import MeshImportError, load_colon_mesh
from tube_set import straight_tube


def _picture(ext: str) -> bytes:
    image = np.random.default_rng(3).integers(0, 256, (40, 60, 3), dtype=np.uint8)
    ok, encoded = cv2.imencode(ext, image)
    assert ok
    return encoded.tobytes()


@pytest.fixture(params=["without charset_normalizer", "with a charset guesser"])
def text_decoder(request, monkeypatch):
    """trimesh decodes a file that is not UTF-8 with charset_normalizer if it is installed:
    the import must say the same either way."""
    if request.param == "without charset_normalizer":
        monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # import fails
    else:
        guesser = types.ModuleType("charset_normalizer")
        guesser.detect = lambda data: {"encoding": "latin-1", "confidence": 0.9}
        monkeypatch.setitem(sys.modules, "charset_normalizer", guesser)
    return request.param


@pytest.mark.parametrize("ext,kind", [(".png", "a PNG image"), (".jpg", "a JPEG image")])
@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".glb"])
def test_a_picture_named_as_a_mesh_is_named_for_what_it_is(tmp_path, text_decoder, ext, kind,
                                                           suffix):
    path = tmp_path / f"scan{suffix}"
    path.write_bytes(_picture(ext))
    with pytest.raises(MeshImportError) as error:
        load_colon_mesh(path)
    message = str(error.value)
    assert message.startswith(f"{path}: {kind}, not a mesh"), message
    assert "\n" not in message and "module" not in message and "OBJ, STL, PLY or GLB" in message


def test_a_binary_stl_whose_header_looks_like_a_picture_is_still_read(tmp_path):
    # A binary STL's 80-byte header is free text; its size and triangle count agree.
    path = tmp_path / "tube.stl"
    straight_tube().export(path)
    data = bytearray(path.read_bytes())
    data[:8] = b"\x89PNG\r\n\x1a\n"
    path.write_bytes(bytes(data))
    assert len(load_colon_mesh(path).faces) == len(straight_tube().faces)


def test_an_obj_in_latin1_is_read(tmp_path, text_decoder):
    """A comment or a name in Latin-1 (an accented letter) makes the file not UTF-8: it
    loaded only where trimesh found charset_normalizer to guess the encoding."""
    tube = straight_tube()
    text = trimesh.exchange.obj.export_obj(tube)
    path = tmp_path / "segmentation.obj"
    path.write_bytes("# côlon segmenté\n".encode("latin-1") + text.encode())
    loaded = load_colon_mesh(path)
    assert len(loaded.faces) == len(tube.faces)
    np.testing.assert_allclose(np.sort(loaded.vertices, axis=0),
                               np.sort(tube.vertices, axis=0), atol=1e-7)


# --- Sizes: a soup refused before the repairs, a mesh beyond the limit before it is read ---

def _soup(triangles: int, seed: int = 0) -> trimesh.Trimesh:
    """`triangles` separate triangles (2 mm) strewn through a 30 x 30 x 9 cm box: each its
    own three vertices, no two sharing one."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.0, 0.3, (triangles, 1, 3)) * [1.0, 1.0, 0.3]
    corners = centres + rng.normal(0.0, 0.002, (triangles, 3, 3))
    return trimesh.Trimesh(corners.reshape(-1, 3), np.arange(3 * triangles).reshape(-1, 3),
                           process=False)


def _stages(path, **options):
    """The import's progress texts, and its error (or None)."""
    from capsule_drake.anatomy.imported import import_colon_mesh

    said = []
    try:
        import_colon_mesh(path, progress=said.append, **options)
    except MeshImportError as e:
        return said, str(e)
    return said, None


def test_a_triangle_soup_is_refused_before_the_repairs(tmp_path):
    """100,000 separate triangles: the import went through the repairs (17 s, 0.6 GB) to
    say '11 open ends'; a million took 117 s and 2.9 GB. It is refused once read, in one
    line saying what it is."""
    path = tmp_path / "soup.obj"
    _soup(100_000).export(path)
    said, error = _stages(path)
    assert error is not None and "\n" not in error
    assert error.startswith(f"{path}: not a tube: its 100,000 triangles fall apart into "
                            "100,000 separate pieces"), error
    assert "a triangle soup" in error and "one connected surface" in error
    assert not any(text.startswith("repairing") for text in said), said


def test_a_wall_with_crumbs_beside_it_is_still_a_wall(tmp_path):
    """A scan's wall with stray fragments beside it (segmentation noise), with its texture
    seams split (here every face its own copies of its vertices, welded only by position),
    or a closed thick wall (an inner and an outer surface, apart) is not in pieces; a wall
    shredded into strips is."""
    from capsule_drake.anatomy.tube_check import check_one_piece

    tube = straight_tube(rings=80, around=48)
    inner = straight_tube(radius=0.018, rings=80, around=48)
    crumbs = _soup(300, seed=1)
    vertices, faces = _joined(tube, inner, crumbs)
    check_one_piece(vertices[faces.reshape(-1)], np.arange(faces.size).reshape(-1, 3))
    check_one_piece(*_joined(tube, crumbs))
    # 40 strips along it, each 2.5 % of the area.
    strips = []
    for k in range(40):
        strip = straight_tube(length=0.3 / 40, rings=3, around=48, start=k * 0.3 / 40)
        strip.vertices[:, 2] += 1e-6 * k  # apart from its neighbours
        strips.append(strip)
    with pytest.raises(MeshImportError, match=r"fall apart into 40 separate pieces, 100% of "
                                              r"the area in pieces of less than 5% of it"):
        check_one_piece(*_joined(*strips))


def _joined(*meshes):
    """(vertices, faces) of the meshes side by side, sharing no vertex index."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    return (np.concatenate([m.vertices for m in meshes]),
            np.concatenate([np.asarray(m.faces) + o for m, o in zip(meshes, offsets)]))


def _big_obj(path, triangles: int):
    """An OBJ of `triangles` faces over three vertices, written in a second."""
    with open(path, "wb") as f:
        f.write(b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0.05\n")
        f.write(b"f 1 2 3\n" * triangles)


def test_a_mesh_beyond_the_import_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    from capsule_drake.anatomy import importer

    path = tmp_path / "huge.obj"
    _big_obj(path, importer.MAX_IMPORT_FACES + 1)
    reads = []
    monkeypatch.setattr(importer, "_read", lambda p: reads.append(p))
    with pytest.raises(MeshImportError) as error:
        load_colon_mesh(path)
    message = str(error.value)
    assert message.startswith(f"{path}: {importer.MAX_IMPORT_FACES + 1:,} triangles, more "
                              f"than the {importer.MAX_IMPORT_FACES:,} the import handles")
    assert "simplify" in message and "\n" not in message
    assert reads == []


def test_an_objs_faces_are_counted_across_the_chunks_it_is_read_in(tmp_path, monkeypatch):
    from capsule_drake.anatomy import importer

    monkeypatch.setattr(importer, "_COUNT_CHUNK", 16)
    for prefix in range(9):  # the chunks' ends at every place in a face's line
        path = tmp_path / f"faces_{prefix}.obj"
        path.write_bytes(b"#" * prefix + b"\nv 0 0 0\nvn 0 0 1\n" + b"f 1 1 1\n" * 50
                         + b"f\t1 1 1\n" + b"# f 1 1 1 is not a face\n")
        assert importer.count_faces(path) == 51, prefix


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".glb"])
def test_the_limit_holds_for_every_format(tmp_path, monkeypatch, suffix):
    """Counted from the header where the format has one (binary STL, PLY), else once
    read (GLB); here against a limit lowered to 1,000."""
    from capsule_drake.anatomy import importer

    monkeypatch.setattr(importer, "MAX_IMPORT_FACES", 1000)
    path = tmp_path / f"tube{suffix}"
    straight_tube(rings=40, around=32).export(path)  # 2,496 faces
    with pytest.raises(MeshImportError, match=r"2,496 triangles, more than the 1,000 the "
                                              r"import handles"):
        load_colon_mesh(path)


@pytest.mark.slow
def test_a_large_import_in_a_run_says_what_it_is_doing(tmp_path, monkeypatch, capsys):
    """Imported on first use in a scenario (no progress bar there), an import of more than
    NOTE_FACES triangles says each stage on stderr as it starts; here with NOTE_FACES
    lowered so that the test's tube counts as large."""
    from capsule_drake.anatomy import imported
    from capsule_drake.anatomy.params import ColonParams, Imported

    monkeypatch.setattr(imported, "NOTE_FACES", 1000)
    path = tmp_path / "tube.obj"
    straight_tube(rings=60, around=32).export(path)
    params = ColonParams(source=Imported(path=str(path)))
    imported.imported_colon_assets(params, cache_dir=tmp_path / "cache")
    lines = capsys.readouterr().err.splitlines()
    stages = [line.split("first use): ", 1)[-1] for line in lines]
    assert all(line.startswith(f"importing {path} (3,776 triangles; cached after this "
                               "first use): ") for line in lines), lines
    for stage in ("reading", "repairing", "centreline", "wall table"):
        assert any(text.startswith(stage) for text in stages), stages
    # A small one says nothing.
    monkeypatch.setattr(imported, "NOTE_FACES", 10_000)
    imported.imported_colon_assets(ColonParams(source=Imported(path=str(path), scale=1.001)),
                                   cache_dir=tmp_path / "cache")
    assert capsys.readouterr().err == ""


def test_a_mesh_that_cannot_be_read_is_one_line_in_a_run(tmp_path, monkeypatch, capsys):
    """A scenario's mesh the user may not read (its permissions; here the read made to
    fail, as the tests may run as root): one line naming it, exit 2, not an internal
    error."""
    from pathlib import Path

    from capsule_drake.app.cli import main

    path = tmp_path / "private.obj"
    straight_tube().export(path)
    read_bytes = Path.read_bytes

    def refuse(self):
        if self.name == "private.obj":
            raise PermissionError(13, "Permission denied", str(self))
        return read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", refuse)
    code = main(["run", "--duration", "0.1", "--no-recording", "--quiet", "--out",
                 str(tmp_path / "out"), "--scenario-text",
                 f"{{colon: {{source: !Imported {{path: {path}}}}}}}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"{path}: cannot be read (Permission denied)" in err[0]
