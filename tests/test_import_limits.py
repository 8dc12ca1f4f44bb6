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
