"""The wall's pressure map as a picture: the colon unrolled (arc length along, the angle
around the centreline up), each patch coloured by its peak pressure and by the longest time
it spent above 30 mmHg (physics/wall_pressure.py), the segments' boundaries and the
anterior wall (toward the EPM) marked. `capsule-sim run` writes it as wall_pressure.png;
the replay page shows it with the capsule's place at the replay's time (io/replay.py).
"""

from __future__ import annotations

import io

import numpy as np

# Peak pressures below this are drawn in the colour scale's first colour (kPa); untouched
# patches (no pressure at all) are left blank.
PEAK_FLOOR_KPA = 1.0
UNTOUCHED = "#d9d9d9"


def anterior_theta_deg(centerline, s) -> np.ndarray:
    """The angle (deg, [-180, 180)) around the centreline at arc length(s) s of the wall that
    faces the patient's front (world +z, toward the EPM above the abdomen), measured as the
    wall's theta is (from the frame's normal toward its binormal); NaN where the centreline
    runs within 25 degrees of vertical (no front wall to speak of)."""
    t, n, b = centerline.frame_at(np.asarray(s, dtype=float))
    up = np.array([0.0, 0.0, 1.0])
    theta = np.mod(np.degrees(np.arctan2(b @ up, n @ up)) + 180.0, 360.0) - 180.0
    return np.where(np.abs(t @ up) < np.cos(np.radians(25.0)), theta, np.nan)


def _broken_at_wraps(x, y, jump=180.0):
    """x, y with NaN inserted where y wraps around (so a line is not drawn across)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    cut = np.flatnonzero(np.abs(np.diff(y)) > jump) + 1
    return np.insert(x, cut, np.nan), np.insert(y, cut, np.nan)


def wall_map_figure(wall, centerline, width: float = 12.0, height: float = 5.6,
                    dpi: int = 100, compact: bool = False):
    """A matplotlib Figure of `wall` (a WallPressure with pressures) on the colon of
    `centerline`: two panels, the peak pressure per patch (kPa, log scale, the thresholds
    marked on its colour bar) and the longest time one patch spent above the ischaemia
    threshold (s); segment boundaries (dashed) and the anterior wall (dotted) on both. The
    angle around runs from -180 to 180 degrees (the patches of 180-360 drawn below 0), so
    that the wall near the frame's normal, which starts anterior at the anus, is not cut.
    `compact`: smaller type, no segment names (the replay's narrow panel). Returns
    (figure, [axes of the two maps])."""
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    s_cm = wall.grid.s_edges * 100.0
    half = wall.grid.n_around // 2
    theta = np.degrees(wall.grid.theta_edges) - np.degrees(wall.grid.theta_edges[half])

    def turned(values):  # columns from theta = -180 (the patches from 180 on first)
        return np.roll(values, -half, axis=1)

    peak_kpa = wall.peak / 1000.0
    name = "ischaemia" if "ischaemia" in wall.longest_above else next(iter(wall.longest_above))
    longest = wall.longest_above[name]
    threshold_kpa = wall.thresholds[name] / 1000.0
    small = 6 if compact else 9
    fig = Figure(figsize=(width, height), dpi=dpi)
    axes = fig.subplots(2, 1, sharex=True)
    top = max(float(peak_kpa.max()), 2.0 * PEAK_FLOOR_KPA)
    panels = (
        (np.ma.masked_less_equal(turned(peak_kpa), 0.0), "magma",
         LogNorm(vmin=PEAK_FLOOR_KPA, vmax=top), "peak pressure (kPa)"),
        (np.ma.masked_less_equal(turned(longest), 0.0), "viridis", None,
         f"longest above {threshold_kpa:.1f} kPa (s)"))
    ranges = centerline.segment_ranges()
    s_fine = np.linspace(0.0, centerline.length, 600)
    for ax, (values, cmap, norm, label) in zip(axes, panels):
        ax.set_facecolor(UNTOUCHED)
        kwargs = {"norm": norm} if norm is not None else {
            "vmin": 0.0, "vmax": max(float(longest.max()), 1e-3)}
        mesh = ax.pcolormesh(s_cm, theta, values.T, cmap=cmap, shading="flat", **kwargs)
        bar = fig.colorbar(mesh, ax=ax, pad=0.01, fraction=0.04)
        bar.set_label(label, fontsize=small)
        bar.ax.tick_params(labelsize=small)
        if norm is not None:  # the thresholds on the pressure's scale
            for level in wall.thresholds.values():
                if PEAK_FLOOR_KPA <= level / 1000.0 <= top:
                    bar.ax.axhline(level / 1000.0, color="cyan", lw=2.0)
        for segment, (start, _) in ranges.items():
            if start > 0.0:
                ax.axvline(start * 100.0, color="0.3", lw=0.8, ls="--")
            if not compact and ax is axes[0]:
                ax.text(start * 100.0 + 0.5, 182.0, segment, fontsize=small - 1,
                        va="bottom", ha="left")
        x, y = _broken_at_wraps(s_fine * 100.0, anterior_theta_deg(centerline, s_fine))
        ax.plot(x, y, color="tab:blue", lw=1.0, ls=":")
        ax.set_ylim(-180.0, 180.0)
        ax.set_yticks([-180, -90, 0, 90, 180])
        ax.set_ylabel("around (deg)", fontsize=small)
        ax.tick_params(labelsize=small)
    axes[1].set_xlim(s_cm[0], s_cm[-1])
    axes[1].set_xlabel("along the colon from the anus (cm)", fontsize=small)
    if not compact:
        injury = wall.thresholds.get("injury")
        title = (f"Wall pressure per {wall.grid.length * 100:.0f} cm x "
                 f"{360 / wall.grid.n_around:.0f} deg patch, sampled every "
                 f"{wall.period * 1000:.0f} ms over {wall.last_time - wall.first_time:.1f} s: "
                 f"peak {peak_kpa.max():.0f} kPa; longest on one patch above "
                 f"{threshold_kpa:.1f} kPa {longest.max():.1f} s"
                 + (f", above {injury / 1000:.0f} kPa "
                    f"{wall.longest_above['injury'].max():.2f} s" if injury else ""))
        fig.suptitle(title, fontsize=small + 1)
        fig.text(0.01, 0.005, "around: from the centreline frame's normal toward its "
                 "binormal (the colon's theta).  Grey: untouched; dashed: segment "
                 "boundaries;\nblue dotted: the anterior wall (toward the EPM); cyan on the "
                 "scale: the thresholds",
                 fontsize=small - 1)
    fig.subplots_adjust(left=0.07 if not compact else 0.15, right=0.98 if not compact else 0.86,
                        top=0.9 if not compact else 0.97,
                        bottom=0.14 if not compact else 0.16, hspace=0.12)
    return fig, list(axes)


def wall_map_png(wall, centerline, **kwargs) -> tuple[bytes, list[list[float]]]:
    """`wall_map_figure` as PNG bytes, with each map's axes box in the image as fractions
    [left, top, right, bottom] from its top left corner (for a cursor drawn over it)."""
    from PIL import Image

    fig, axes = wall_map_figure(wall, centerline, **kwargs)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    # A palette of 256 colours: a third of the size (the maps' colour scales and the
    # text's grey levels fit in it).
    image = Image.open(io.BytesIO(buffer.getvalue())).convert("RGB").quantize(colors=256)
    buffer = io.BytesIO()
    image.save(buffer, format="png", optimize=True)
    boxes = []
    for ax in axes:
        box = ax.get_position()
        boxes.append([box.x0, 1.0 - box.y1, box.x1, 1.0 - box.y0])
    return buffer.getvalue(), boxes


def write_wall_map(path, wall, centerline) -> None:
    """wall_pressure.png at `path` (through the caller's temporary file)."""
    png, _ = wall_map_png(wall, centerline)
    with open(path, "wb") as f:
        f.write(png)
