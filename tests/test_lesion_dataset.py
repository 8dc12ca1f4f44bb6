"""A recorded dataset's lesion ground truth (app/lesion_dataset.py), read with pycocotools:
the COCO file loads, and each annotation's mask decodes to exactly the pixels of that
polyp in the frame's mask PNG; our RLE encoder against pycocotools' own; the MCAP log's
lesion boxes against the dataset's."""

import csv
import json

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from pycocotools import mask as coco_mask
from pycocotools.coco import COCO

from capsule_drake.app.cli import main as cli_main
from capsule_drake.app.lesion_dataset import box_of, rle_encode

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:pycocotools")

SEED = 4
# A sessile polyp on the wall of the rectum where the default capsule looks at it.
TEXT = ("{colon: {lesions: {drawn: false, placed: [{kind: 0-Is, size_mm: 10, "
        "segment: rectum, along: 0.3, around_deg: 200}, {kind: 0-Ip, size_mm: 7, "
        "segment: rectum, along: 0.45, around_deg: 60}, {kind: diverticulum, size_mm: 8, "
        "segment: rectum, along: 0.4, around_deg: 300}]}}}")


@pytest.mark.parametrize("shape, fill", [((5, 7), "random"), ((64, 48), "random"),
                                         ((16, 16), "empty"), ((16, 16), "full"),
                                         ((9, 4), "first")])
def test_our_rle_is_pycocotools_rle(shape, fill):
    rng = np.random.default_rng(sum(shape))
    mask = {"random": rng.uniform(size=shape) < 0.3, "empty": np.zeros(shape, bool),
            "full": np.ones(shape, bool)}.get(fill)
    if fill == "first":
        mask = np.zeros(shape, bool)
        mask[0, 0] = mask[3, 2] = True
    ours = rle_encode(mask)
    theirs = coco_mask.encode(np.asfortranarray(mask.astype(np.uint8)))
    assert ours["counts"] == theirs["counts"].decode()
    assert ours["size"] == list(theirs["size"])
    np.testing.assert_array_equal(coco_mask.decode(
        {"size": ours["size"], "counts": ours["counts"].encode()}), mask)
    if mask.any():
        assert box_of(mask) == list(coco_mask.toBbox(theirs))


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("lesions") / "recording"
    text = TEXT.replace("{colon: {", f"{{colon: {{seed: {SEED}, ", 1)
    code = cli_main(["record", "--duration", "0.35", "--scenario-text", text, "--out",
                     str(out), "--mcap", str(out.parent / "run.mcap"), "--quiet"])
    assert code == 0
    return out


@pytest.mark.slow
def test_the_coco_file_loads_and_its_masks_are_the_mask_pngs(folder):
    coco = COCO(str(folder / "lesions_coco.json"))
    frames = sorted((folder / "Frames").glob("FrameBuffer_*.png"))
    assert len(coco.getImgIds()) == len(frames) >= 3
    assert {c["name"] for c in coco.loadCats(coco.getCatIds())} == {"0-Ip", "0-Is", "0-IIa",
                                                                     "diverticulum"}
    annotated = 0
    for image in coco.loadImgs(coco.getImgIds()):
        assert (folder / image["file_name"]).exists()
        instances = cv2.imread(str(folder / "Frames" / f"Lesions_{image['id']:04d}.png"),
                               cv2.IMREAD_UNCHANGED)
        assert instances.dtype == np.uint16
        annotations = coco.loadAnns(coco.getAnnIds(imgIds=image["id"]))
        assert sorted(a["lesion_index"] + 1 for a in annotations) == sorted(
            v for v in np.unique(instances) if v)
        for a in annotations:
            mask = coco.annToMask(a).astype(bool)
            np.testing.assert_array_equal(mask, instances == a["lesion_index"] + 1)
            assert a["area"] == int(mask.sum())
            assert a["bbox"] == box_of(mask)
            annotated += 1
    assert annotated >= 3       # the sessile polyp is in view from the start
    rows = list(csv.DictReader(open(folder / "lesions.csv")))
    assert [r["paris_type"] for r in rows] == ["0-Is", "0-Ip", "diverticulum"]
    readme = (folder / "README.md").read_text()
    for name in ("Lesions_XXXX.png", "lesions.csv", "lesion_frames.csv", "lesions_coco.json"):
        assert name in readme
    shown = json.loads((folder / "lesions_coco.json").read_text())["annotations"]
    for row in rows:
        count = sum(a["lesion_index"] == int(row["polyp"]) for a in shown)
        assert int(row["frames_shown"]) == count


@pytest.mark.slow
def test_the_mcap_log_boxes_the_polyps_the_dataset_annotates(folder):
    """/capsule/lesions/marker: per frame, each polyp in view as a box, the same boxes as
    the dataset's lesion_frames.csv of the same run."""
    boxes = {}
    with open(folder.parent / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, marker in reader.iter_decoded_messages(
                topics=["/capsule/lesions/marker"]):
            if marker.action == 0:
                stamp = marker.header.stamp.sec + 1e-9 * marker.header.stamp.nanosec
                xs = [p.x for p in marker.points]
                ys = [p.y for p in marker.points]
                boxes[(round(stamp, 4), marker.id)] = (min(xs) + 0.5, min(ys) + 0.5,
                                                       max(xs) - min(xs), max(ys) - min(ys))
    times = {int(r["index"]): float(r["time_s"])
             for r in csv.DictReader(open(folder / "frames.csv"))}
    expected = {(round(times[int(r["frame"])], 4), int(r["polyp"])): tuple(
        float(r[k]) for k in ("box_x_px", "box_y_px", "box_w_px", "box_h_px"))
        for r in csv.DictReader(open(folder / "lesion_frames.csv"))}
    assert expected and boxes == expected
