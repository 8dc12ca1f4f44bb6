"""A picture of a run as a live Foxglove client saw it (docs/live_client.png).

Starts `capsule-sim run --scenario WithSensors --foxglove` and, beside it, the client made of
Foxglove's own packages (tests/foxglove_client, under node), which subscribes to every
channel and keeps the last message of each topic it decoded. Draws from those decoded
messages only: the camera image with the lumen tracker's and the truth's pixels, and the 3D
scene (/scene/markers: the colon's wall, the capsule and the EPM, placed by the last /tf).

Run: python benchmarks/live_client_picture.py [--seconds 6] [--out docs/live_client.png]
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CLIENT = ROOT / "tests" / "foxglove_client"


def watch(seconds: float, folder: Path) -> dict:
    """Runs the simulation and the client; returns {topic: last decoded message}."""
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--silent"], cwd=CLIENT,
                       check=True, timeout=600)
    run = subprocess.Popen(
        [sys.executable, "-m", "capsule_drake.app", "run", "--scenario", "WithSensors",
         "--duration", str(seconds), "--foxglove", "0", "--no-recording", "--quiet",
         "--out", str(folder / "run"), "--scenario-text",
         "{outputs: {foxglove: {wait_for_client: 120}}}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    for line in run.stdout:
        found = re.search(r"ws://127\.0\.0\.1:(\d+)", line)
        if found:
            break
    else:
        sys.exit("live_client_picture: the run did not start its Foxglove server")
    dump = folder / "seen"
    subprocess.run(["node", str(CLIENT / "client.mjs"), f"ws://127.0.0.1:{found.group(1)}",
                    str(seconds * 20 + 120), "/never"], capture_output=True, text=True,
                   env=dict(os.environ, CAPSULE_CLIENT_DUMP=str(dump)), timeout=seconds * 20 + 180)
    run.communicate(timeout=600)
    return {path.stem: json.loads(path.read_text()) for path in dump.glob("*.json")}


def quaternion_matrix(q) -> np.ndarray:
    x, y, z, w = q["x"], q["y"], q["z"], q["w"]
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def draw(seen: dict, out: Path) -> None:
    image = seen["_capsule_camera_image_raw"]
    pixels = np.array(image["data"], dtype=np.uint8).reshape(image["height"], image["width"], 3)
    figure = plt.figure(figsize=(11, 5), dpi=110)
    left = figure.add_subplot(1, 2, 1)
    left.imshow(pixels)
    for topic, colour, label in (("_capsule_lumen_tracker_pixel", "lime", "lumen tracker"),
                                 ("_capsule_lumen_truth_far_pixel", "magenta", "lumen truth")):
        point = seen.get(topic, {}).get("point")
        # (the tracker's z is its confidence, its x null when it found none; the truth's z
        # is 1 when the lumen is in view)
        if point and point.get("x") is not None and ("tracker" in topic or point["z"] > 0.5):
            left.plot(point["x"], point["y"], "o", mfc="none", mec=colour, ms=14, mew=2,
                      label=label)
    stamp = image["header"]["stamp"]
    left.set_title(f"/capsule/camera/image_raw (sensor_msgs/Image, rgb8), "
                   f"t = {stamp['sec'] + 1e-9 * stamp['nanosec']:.2f} s", fontsize=9)
    left.legend(loc="lower right", fontsize=8)
    left.axis("off")

    right = figure.add_subplot(1, 2, 2, projection="3d")
    markers = seen["_scene_markers"]["markers"]
    wall = next(m for m in markers if m["ns"] == "colon_wall")
    points = np.array([[p["x"], p["y"], p["z"]] for p in wall["points"]])
    triangles = points.reshape(-1, 3, 3)
    keep = triangles[:: max(1, len(triangles) // 12000)]
    right.add_collection3d(Poly3DCollection(keep, facecolor=(0.8, 0.45, 0.4, 0.25),
                                            edgecolor="none"))
    poses = {t["child_frame_id"]: t["transform"] for t in seen["_tf"]["transforms"]}
    for frame, colour, size, label in (("capsule", "red", 60, "capsule (/tf)"),
                                       ("epm", "royalblue", 120, "EPM (/tf)")):
        p = poses[frame]["translation"]
        right.scatter([p["x"]], [p["y"]], [p["z"]], c=colour, s=size, label=label,
                      depthshade=False)
    p, e = poses["capsule"]["translation"], poses["epm"]["translation"]
    gap = np.linalg.norm([e[k] - p[k] for k in "xyz"])
    right.plot([p["x"], e["x"]], [p["y"], e["y"]], [p["z"], e["z"]], "k--", lw=1)
    right.text(e["x"], e["y"], (p["z"] + e["z"]) / 2, f"  {100 * gap:.0f} cm", fontsize=8)
    axis = quaternion_matrix(poses["capsule"]["rotation"])[:, 2]
    right.quiver(p["x"], p["y"], p["z"], *(0.05 * axis), color="red")
    low, high = points.min(axis=0), points.max(axis=0)
    high[2] = max(high[2], poses["epm"]["translation"]["z"])
    centre, half = (low + high) / 2, (high - low).max() / 2
    for set_limits, c in zip((right.set_xlim, right.set_ylim, right.set_zlim), centre):
        set_limits(c - half, c + half)
    right.view_init(elev=20, azim=-50)
    right.set_title(f"/scene/markers: the colon's wall ({len(triangles)} triangles), "
                    "capsule and EPM at /tf", fontsize=9)
    right.legend(loc="upper left", fontsize=8)
    right.set_xlabel("x (m)")
    right.set_ylabel("y (m)")
    right.set_zlabel("z (m)")
    figure.suptitle("A running simulation as a Foxglove WebSocket client decoded it "
                    "(@foxglove/ws-protocol, rosmsg2-serialization, under node)", fontsize=10)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    print(f"wrote {out}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "live_client.png")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        seen = watch(args.seconds, Path(folder))
        draw(seen, args.out)


if __name__ == "__main__":
    main()
