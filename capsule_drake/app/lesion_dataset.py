"""Lesion ground truth of a recorded dataset: per-frame instance masks and a COCO file.

Written beside the frames (app/dataset.py) when the colon has polyps or diverticula (a
diverticulum counts as a lesion like a polyp: its mask is the sac seen through its neck, its
"Paris type" and size class "diverticulum", its size the neck's diameter):

    Frames/Lesions_0000.png   16-bit instance mask: 0 where no polyp is seen, k + 1 where
                              polyp k (its index in lesions.csv) is
    lesions.csv               per polyp: index, Paris type, size (mm), size class, segment,
                              arc length of its foot (m), its top (m, world), frames that show
                              it, their largest pixel area
    lesion_frames.csv         per frame and polyp seen: frame, polyp, pixel area, box
    lesions_coco.json         COCO instances: images (the colour frames), categories (the
                              Paris types), one annotation per polyp per frame it is seen in
                              (its mask as compressed RLE, its box and area, and the lesion's
                              index, size, size class and segment)

The masks come from the camera's label image (`CapsuleCamera`'s label_image: each polyp has
its own render label, LESION_LABEL_BASE + its index), so the COCO masks decode to exactly the
pixels of the mask PNGs (tested with pycocotools). Every per-frame row is written and
flushed as the run goes; the COCO file, which holds them all, is written at the end (and
rebuilt from lesion_frames.jsonl by `write_coco` if a run was cut off).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np

from capsule_drake.capsule.camera_walls import lesion_labels

PARIS_CATEGORIES = {"0-Ip": 1, "0-Is": 2, "0-IIa": 3, "diverticulum": 4}
"""COCO category id of each Paris type (supercategory "polyp") and of a diverticulum
(supercategory "diverticulum")."""


def rle_encode(mask: np.ndarray) -> dict:
    """COCO's compressed RLE of a binary mask (H, W): run lengths over the column-major
    pixels starting with a run of zeros, each written (as its difference from the run two
    before, from the third on) in 5-bit groups with a continuation bit, plus 48 (the COCO
    API's rleToString)."""
    h, w = mask.shape
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    counts = list(np.diff(bounds))
    if flat.size and flat[0]:
        counts = [0] + counts
    chars = []
    for i, count in enumerate(counts):
        x = int(count) - (int(counts[i - 2]) if i > 2 else 0)
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if (c & 0x10) else (x != 0)
            if more:
                c |= 0x20
            chars.append(chr(c + 48))
    return {"size": [int(h), int(w)], "counts": "".join(chars)}


def box_of(mask: np.ndarray) -> list[float]:
    """[x, y, width, height] of the mask's pixels (COCO's box, in pixels)."""
    rows, cols = np.nonzero(mask)
    return [float(cols.min()), float(rows.min()), float(cols.max() - cols.min() + 1),
            float(rows.max() - rows.min() + 1)]


class LesionRecorder:
    """Writes the lesion files of a dataset frame by frame (module docstring).

    Args:
        out_dir: the dataset folder (Frames/ exists).
        polyps: the placed polyps (anatomy/lesion_geometry.PlacedPolyp), by index; the
            camera's label image labels them (`capsule.camera.lesion_labels`).
    """

    def __init__(self, out_dir, polyps):
        self._out = Path(out_dir)
        self._labels = lesion_labels(polyps)
        self._polyps = {p.index: p for p in polyps}
        self._size = (0, 0)   # (width, height) of the frames, from the first one
        self._frames_shown = {k: 0 for k in self._polyps}
        self._largest = {k: 0 for k in self._polyps}
        self._lookup = np.zeros(1 << 16, dtype=np.uint16)   # label (as uint16) -> k + 1
        for label, k in self._labels.items():
            self._lookup[np.uint16(label)] = k + 1
        self._frames_file = open(self._out / "lesion_frames.csv", "w", newline="")
        self._frames_csv = csv.writer(self._frames_file)
        self._frames_csv.writerow(["frame", "polyp", "pixel_area", "box_x_px", "box_y_px",
                                   "box_w_px", "box_h_px"])
        self._jsonl = open(self._out / "lesion_frames.jsonl", "w")
        self._frames_file.flush()

    def add(self, index: int, file_name: str, label_image: np.ndarray) -> None:
        """Frame `index` (its colour file `file_name`): writes its mask PNG and rows."""
        instances = self._lookup[np.asarray(label_image).astype(np.uint16)]
        self._size = (instances.shape[1], instances.shape[0])
        path = self._out / "Frames" / f"Lesions_{index:04d}.png"
        if not cv2.imwrite(str(path), instances):
            raise OSError(f"could not write {path}")
        annotations = []
        for value in np.unique(instances):
            if value == 0:
                continue
            k = int(value) - 1
            mask = instances == value
            area = int(mask.sum())
            box = box_of(mask)
            self._frames_shown[k] += 1
            self._largest[k] = max(self._largest[k], area)
            self._frames_csv.writerow([index, k, area, *(f"{b:.0f}" for b in box)])
            annotations.append({"polyp": k, "area": area, "bbox": box,
                                "segmentation": rle_encode(mask)})
        self._frames_file.flush()
        self._jsonl.write(json.dumps({"frame": index, "file_name": file_name,
                                      "annotations": annotations}) + "\n")
        self._jsonl.flush()

    def close(self) -> None:
        """Writes lesions.csv and lesions_coco.json; closes the files."""
        for f in (self._frames_file, self._jsonl):
            if not f.closed:
                f.close()
        with open(self._out / "lesions.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["polyp", "paris_type", "size_mm", "size_class", "segment", "s_m",
                             "top_x_m", "top_y_m", "top_z_m", "frames_shown",
                             "largest_pixel_area"])
            for k, polyp in sorted(self._polyps.items()):
                top = polyp.top_W
                writer.writerow([k, polyp.lesion.kind, f"{polyp.lesion.size_mm:.2f}",
                                 polyp.lesion.size_class, polyp.lesion.segment,
                                 f"{polyp.s:.4f}", *(f"{c:.5f}" for c in top),
                                 self._frames_shown[k], self._largest[k]])
        write_coco(self._out, self._polyps, self._size)


def write_coco(out_dir, polyps, image_size) -> Path:
    """lesions_coco.json from lesion_frames.jsonl (every frame is an image, with or without
    polyps)."""
    out = Path(out_dir)
    width, height = image_size
    polyps = polyps if isinstance(polyps, dict) else {p.index: p for p in polyps}
    images, annotations = [], []
    with open(out / "lesion_frames.jsonl") as f:
        for line in f:
            frame = json.loads(line)
            images.append({"id": frame["frame"], "file_name": frame["file_name"],
                           "width": width, "height": height})
            for a in frame["annotations"]:
                lesion = polyps[a["polyp"]].lesion
                annotations.append({
                    "id": len(annotations) + 1, "image_id": frame["frame"],
                    "category_id": PARIS_CATEGORIES[lesion.kind], "iscrowd": 0,
                    "area": a["area"], "bbox": a["bbox"], "segmentation": a["segmentation"],
                    "lesion_index": a["polyp"], "size_mm": round(lesion.size_mm, 2),
                    "size_class": lesion.size_class, "segment": lesion.segment})
    coco = {"info": {"description": "capsule_drake lesion ground truth (app/lesion_dataset.py)"},
            "images": images, "annotations": annotations,
            "categories": [{"id": i, "name": name,
                            "supercategory": "diverticulum" if name == "diverticulum" else "polyp"}
                           for name, i in PARIS_CATEGORIES.items()]}
    path = out / "lesions_coco.json"
    path.write_text(json.dumps(coco))
    return path
