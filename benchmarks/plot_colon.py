"""Draw procedural colons (frontal and lateral projections) and a shaded wall close-up.

Usage: python benchmarks/plot_colon.py [--seeds 0 1 2] [--out colon_layout.png]
       [--mesh-out colon_mesh.png] [--population "{sex: female, sigmoid: redundant}"]

--population draws the seeds' patients from the population (anatomy/population.py) with
the traits given as YAML (`{}`: anyone).

Frontal view (x-y): seen from the front, head up, patient's left on the image right; grey
lines are the torso's flanks. Lateral view (y-z): head to the right, anterior up; the grey
curve is the anterior skin on the midline, the black line the table top. Segments are
coloured rectum to cecum: red, orange, green, blue, magenta, teal. The mesh figure shows the
wall unrolled (arc length to the right, angle down: crescent folds between the three
taeniae) and a shaded view from inside the ascending colon. Prints build times.
"""

import argparse
import time

import cv2
import numpy as np

from pydrake.common.yaml import yaml_load_typed

from capsule_drake.anatomy import SEGMENT_NAMES, ColonParams, build_colon
from capsule_drake.anatomy.params import Population, Procedural

# BGR colours per segment, rectum to cecum.
COLOURS = [(60, 60, 220), (0, 160, 255), (0, 190, 0), (220, 110, 0), (200, 0, 200),
           (120, 120, 0)]
PANEL = 560
SCALE = 950.0  # px per metre


def _frontal(p, row):
    return (int(PANEL / 2 + p[0] * SCALE), int(row * PANEL + PANEL * 0.55 - p[1] * SCALE))


def _lateral(p, row):
    return (int(PANEL + PANEL / 2 + p[1] * SCALE), int(row * PANEL + PANEL - 30 - p[2] * SCALE))


def draw_layouts(seeds, population=None):
    img = np.full((PANEL * len(seeds), 2 * PANEL, 3), 255, np.uint8)
    for row, seed in enumerate(seeds):
        t0 = time.perf_counter()
        colon = build_colon(ColonParams(seed=seed, source=population or Procedural()))
        build_s = time.perf_counter() - t0
        cl = colon.centerline
        pts, seg, rad = cl.points[::3], cl.segment[::3], cl.radius[::3]
        # Skin: frontal outline at the table edge is the torso width; lateral = midline.
        ab = colon.abdomen
        y = np.linspace(ab.params.torso_y_min, ab.params.torso_y_max, 100)
        skin = np.stack([np.zeros_like(y), y, ab.skin_height(0.0, y)], axis=1)
        cv2.polylines(img, [np.array([_lateral(q, row) for q in skin])], False,
                      (150, 150, 150), 2, cv2.LINE_AA)
        table = np.array([[0, y[0], 0.0], [0, y[-1], 0.0]])
        cv2.line(img, _lateral(table[0], row), _lateral(table[1], row), (0, 0, 0), 1)
        for side in (-1, 1):
            edge = np.stack([np.full_like(y, side * ab.params.half_width), y, y * 0], 1)
            cv2.polylines(img, [np.array([_frontal(q, row) for q in edge])], False,
                          (150, 150, 150), 2, cv2.LINE_AA)
        for view in (_frontal, _lateral):
            for k in range(len(pts) - 1):
                width = max(1, int(2 * rad[k] * SCALE * 0.5))
                cv2.line(img, view(pts[k], row), view(pts[k + 1], row), COLOURS[seg[k]],
                         width, cv2.LINE_AA)
            cv2.polylines(img, [np.array([view(q, row) for q in pts])], False, (40, 40, 40),
                          1, cv2.LINE_AA)
        lengths = colon.segment_lengths()
        text = f"seed {seed}: {cl.length * 100:.1f} cm, built in {build_s:.2f} s"
        cv2.putText(img, text, (8, row * PANEL + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, "frontal (patient left ->)", (8, row * PANEL + 40),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (80, 80, 80), 1, cv2.LINE_AA)
        cv2.putText(img, "lateral (head ->, anterior up)", (PANEL + 8, row * PANEL + 20),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (80, 80, 80), 1, cv2.LINE_AA)
        for k, name in enumerate(SEGMENT_NAMES):
            cv2.putText(img, f"{name} {lengths[name] * 100:.1f}",
                        (8, row * PANEL + PANEL - 110 + 16 * k), cv2.FONT_HERSHEY_SIMPLEX,
                        0.42, COLOURS[k], 1, cv2.LINE_AA)
        print(f"seed {seed}: build_colon {build_s:.3f} s, total {cl.length * 100:.1f} cm, "
              + ", ".join(f"{n} {lengths[n] * 100:.1f}" for n in SEGMENT_NAMES))
    return img


def draw_mesh_closeup(colon, s0: float, s1: float, size=(900, 500)):
    """Lambert-shaded inside view of the wall between s0 and s1 (a cut-open tube).

    The stretch is unrolled: arc length to the right, theta down, shaded by the angle
    between the wall normal and a light along the centreline frame's normal.
    """
    p = colon.params
    s = np.arange(s0, s1, p.visual_axial_step)
    theta = np.linspace(-np.pi, np.pi, 256)
    w = colon.wall_radius(s[None, :], theta[:, None])
    # Shade by the slope of the wall: folds catch the light on one flank.
    dws = np.gradient(w, s, axis=1)
    dwt = np.gradient(w, theta, axis=0) / np.maximum(w, 1e-3)
    normal = np.stack([-dws, -dwt, np.ones_like(w)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.array([-0.6, -0.3, 0.75])
    light /= np.linalg.norm(light)
    shade = np.clip(normal @ light, 0.0, 1.0)
    base = np.array([80, 95, 205], float)  # BGR mucosa
    img = (shade[..., None] * base).astype(np.uint8)
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def draw_render(colon, size=500):
    """Endoscope-like view of the visual mesh in the ascending colon (painter's algorithm).

    Eye on the centreline looking toward the cecum, light at the eye with 1/d^2 falloff:
    the dark lumen ahead and the lit folds around it.
    """
    mesh = colon.visual_mesh()
    cl = colon.centerline
    s_eye = cl.segment_ranges()["ascending"][0] + 0.03
    eye = cl.point_at(s_eye)
    t, n, b = cl.frame_at(s_eye)
    tri = mesh.triangles - eye
    z = tri @ t
    keep = np.all(z > 0.003, axis=1) & np.all(z < 0.20, axis=1)
    tri, z = tri[keep], z[keep]
    x, y = tri @ n, tri @ b
    f = size * 0.45
    uv = np.stack([size / 2 + f * x / z, size / 2 + f * y / z], axis=-1)
    centre = tri.mean(axis=1)
    dist = np.linalg.norm(centre, axis=1)
    normals = mesh.face_normals[keep]
    lam = np.clip(-np.sum(normals * centre, axis=1) / dist, 0.0, 1.0)
    light = lam / (1.0 + (dist / 0.04) ** 2)
    img = np.zeros((size, size, 3), np.uint8)
    base = np.array([90, 110, 235], float)
    for k in np.argsort(-dist):
        colour = tuple(int(c) for c in light[k] * base)
        cv2.fillConvexPoly(img, np.round(uv[k] * 16).astype(np.int32), colour,
                           cv2.LINE_AA, 4)
    return img


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default="colon_layout.png")
    parser.add_argument("--mesh-out", default="colon_mesh.png")
    parser.add_argument("--population", default=None,
                        help="draw the patients from the population, with these traits (YAML)")
    args = parser.parse_args()
    population = (yaml_load_typed(schema=Population, data=args.population)
                  if args.population is not None else None)
    cv2.imwrite(args.out, draw_layouts(args.seeds, population))
    print(f"wrote {args.out}")

    colon = build_colon(ColonParams(seed=args.seeds[0], source=population or Procedural()))
    t0 = time.perf_counter()
    visual = colon.visual_mesh()
    chunks = colon.collision_meshes()
    print(f"meshes {time.perf_counter() - t0:.3f} s: visual {len(visual.faces)} triangles, "
          f"collision {sum(len(c.faces) for c in chunks)} triangles in {len(chunks)} chunks")
    ranges = colon.centerline.segment_ranges()
    a, _ = ranges["ascending"]
    strip = draw_mesh_closeup(colon, a - 0.06, a + 0.10)
    render = draw_render(colon, size=strip.shape[0])
    cv2.imwrite(args.mesh_out, np.concatenate([strip, render], axis=1))
    print(f"wrote {args.mesh_out}")


if __name__ == "__main__":
    main()
