"""Rendered views along the colon, the lumen cue they carry, and `record`'s output folder."""

import numpy as np
import pytest

from capsule_drake.anatomy import load_colon
from capsule_drake.app.cli import main as cli_main
from capsule_drake.perception.views import darkest_spot, views_along_colon
from capsule_drake.scenario import load_scenario


@pytest.fixture(scope="module")
def views():
    scenario = load_scenario()
    colon, _ = load_colon(scenario.colon)
    length = colon.centerline.length
    return views_along_colon(scenario, np.linspace(0.1, length - 0.1, 8))


def test_darkest_region_lies_near_the_lumen_truth(views):
    # With the light at the lens and distance falloff, the darkest spot of the image is the
    # deepest place: the lumen (sources.md s. 5). Over views along the whole colon it lies
    # within a tenth of the image diagonal of the lumen truth (5 cm ahead on the centerline).
    diagonal = np.hypot(256, 256)
    gaps = []
    for view in views:
        assert view.lumen_visible, view.segment
        gaps.append(np.linalg.norm(darkest_spot(view.rgb, view.mask) - view.lumen_pixel))
    gaps = np.array(gaps) / diagonal
    print("darkest spot to lumen truth / diagonal:", np.round(gaps, 3))
    assert np.median(gaps) < 0.08 and gaps.max() < 0.15


def test_depth_is_deepest_at_the_lumen(views):
    for view in views:
        u, v = np.round(view.lumen_pixel).astype(int)
        near_lumen = view.depth[max(v - 3, 0):v + 4, max(u - 3, 0):u + 4]
        seen = view.depth[view.mask & np.isfinite(view.depth)]
        assert np.nanmedian(np.where(np.isfinite(near_lumen), near_lumen, 0.3)) > \
            np.percentile(seen, 75)


# What a recorded dataset holds is tested in test_dataset_folder.py.


def test_record_refuses_a_non_empty_folder(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("data")
    assert cli_main(["record", "--duration", "0.1", "--out", str(tmp_path)]) == 2
    assert "folder exists and holds keep.txt" in capsys.readouterr().err
