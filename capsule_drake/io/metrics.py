"""What a run achieved, computed from its logs and the colon's ground truth."""

from __future__ import annotations

import numpy as np

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.epm.guard import GUARD_COUNTS
from capsule_drake.epm.poses import skin_gap
from capsule_drake.physics.tissue import PRESSURE_THRESHOLDS, time_above


def capsule_surface_points_C(radius: float, length: float, n_around: int = 24) -> np.ndarray:
    """Points on a capsule's surface in its own frame (axis z, cylinder of `length`).

    Rings on the cylinder (at most 2 mm apart, so a fold crest crossing under the capsule is
    not missed) and on both hemispherical caps (every 22.5 degrees of elevation), plus the
    two tips: with 24 points around, the farthest point in any direction is found to within
    r (1 - cos 7.5 deg) ~ 0.05 mm.
    """
    angles = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    ring = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    points = []
    half = 0.5 * length
    for z in np.linspace(-half, half, int(np.ceil(length / 0.002)) + 1):
        points.append(radius * ring + [0.0, 0.0, z])
    for sign in (-1.0, 1.0):
        for elevation in np.deg2rad([22.5, 45.0, 67.5]):
            cap = radius * np.column_stack([np.cos(elevation) * ring[:, 0],
                                            np.cos(elevation) * ring[:, 1],
                                            np.full(n_around, sign * np.sin(elevation))])
            points.append(cap + [0.0, 0.0, sign * half])
        points.append([[0.0, 0.0, sign * (half + radius)]])
    return np.vstack(points)


def capsule_poses(state_log: np.ndarray):
    """Rotation matrices (K, 3, 3) and positions (K, 3) from logged capsule states (13, K)."""
    R = np.array([rotation_from_quaternion(q) for q in state_log[:4].T])
    return R, state_log[4:7].T.copy()


EXCURSION_CHUNK_POINTS = 200_000
"""Surface points measured at once by wall_excursion: a long run logged finely (240,000
poses of a 60 s run at 0.25 ms) would otherwise ask for tens of GB at once."""


def wall_excursion(colon, R_WC: np.ndarray, p_WC: np.ndarray, points_C: np.ndarray) -> np.ndarray:
    """Per pose, how far the capsule reaches beyond the colon wall (m; <= 0 means inside).
    Measured a chunk of poses at a time (EXCURSION_CHUNK_POINTS surface points)."""
    out = np.empty(len(p_WC))
    step = max(1, EXCURSION_CHUNK_POINTS // max(len(points_C), 1))
    for k in range(0, len(p_WC), step):
        R, p = R_WC[k:k + step], p_WC[k:k + step]
        points_W = np.einsum("kij,nj->kni", R, points_C) + p[:, None, :]
        out[k:k + step] = colon.excursion(points_W.reshape(-1, 3)).reshape(
            len(p), len(points_C)).max(axis=1)
    return out


# What a run achieved along and against the colon: not reported for a run that diverged.
OUTCOMES = ("final_s_m", "max_s_m", "advance_m", "stop_segment", "peak_contact_force_N",
            "max_wall_excursion_m", "time_of_max_wall_excursion_s", "min_epm_capsule_distance_m",
            "peak_contact_pressure_kPa", "time_above_injury_pressure_s",
            "time_above_ischaemia_pressure_s")

# The wall's patches (physics/wall_pressure.py): what each went through, the worst of them.
SITE_OUTCOMES = ("site_peak_pressure_kPa", "site_peak_at_s_m", "site_peak_at_theta_deg",
                 "site_peak_segment", "site_longest_above_injury_s",
                 "site_longest_above_ischaemia_s", "site_longest_above_ischaemia_at_s_m",
                 "site_longest_above_ischaemia_segment", "sites_above_injury",
                 "sites_above_ischaemia")


def pressure_metrics(times, contact_pressure) -> dict:
    """The contact's peak pressure (kPa) over a run's samples and the seconds spent above
    each threshold of physics/tissue.py (`time_above_<name>_pressure_s`: injury 330 kPa,
    ischaemia 4.0 kPa). None where nothing was measured: no samples, or point contact (NaN
    samples: it has no pressure field; one is enough, the samples before the capsule
    touched the wall being 0)."""
    names = [f"time_above_{name}_pressure_s" for name in PRESSURE_THRESHOLDS]
    pressure = np.asarray(contact_pressure, dtype=float) if contact_pressure is not None else None
    if pressure is None or pressure.size == 0 or np.any(np.isnan(pressure)):
        return {"peak_contact_pressure_kPa": None, **{name: None for name in names}}
    return {"peak_contact_pressure_kPa": float(np.nanmax(pressure)) / 1000.0,
            **{name: time_above(times, pressure, threshold)
               for name, threshold in zip(names, PRESSURE_THRESHOLDS.values())}}


def site_pressure_metrics(wall, centerline) -> dict:
    """The wall's patches' figures (physics/wall_pressure.py `WallPressure`, on the colon's
    `centerline`), as metrics (SITE_OUTCOMES and the patch size):

    - site_peak_pressure_kPa: the highest pressure any patch felt; site_peak_at_s_m,
      site_peak_at_theta_deg, site_peak_segment: that patch's centre and segment;
    - site_longest_above_<name>_s (injury 330 kPa, ischaemia 4.0 kPa): the longest time ONE
      patch spent above the threshold without a break; for ischaemia, where that patch is
      (site_longest_above_ischaemia_at_s_m, _segment; null if none went above);
    - sites_above_<name>: how many patches went above the threshold;
    - wall_pressure_field: whether the contact has a pressure field (false: point contact);
      wall_patch_length_m, wall_patch_angle_deg, wall_pressure_period_s: the patches and
      how often they were sampled.

    All null without a map (None) or without pressures in it (point contact has no
    pressure field)."""
    figures = {key: None for key in SITE_OUTCOMES}
    if wall is None:
        return figures
    figures.update(wall_pressure_field=wall.pressure_field,
                   wall_patch_length_m=wall.grid.length,
                   wall_patch_angle_deg=360.0 / wall.grid.n_around,
                   wall_pressure_period_s=wall.period)
    if not wall.has_pressure:
        return figures

    def where(flat):
        i, j = np.unravel_index(int(flat), wall.grid.shape)
        s, theta = wall.patch_centre(i, j)
        return s, theta, centerline.segment_at(s)

    peak = wall.peak
    s, theta, segment = where(np.argmax(peak))
    figures.update(site_peak_pressure_kPa=float(peak.max()) / 1000.0, site_peak_at_s_m=s,
                   site_peak_at_theta_deg=theta, site_peak_segment=segment)
    for name, threshold in wall.thresholds.items():
        longest = wall.longest_above[name]
        figures[f"site_longest_above_{name}_s"] = float(longest.max())
        figures[f"sites_above_{name}"] = int(np.sum(peak > threshold))
    longest = wall.longest_above.get("ischaemia")
    if longest is not None and longest.max() > 0.0:
        # The longest press, the higher peak among patches pressed as long.
        flat = np.lexsort((peak.ravel(), longest.ravel()))[-1]
        s, _, segment = where(flat)
        figures.update(site_longest_above_ischaemia_at_s_m=s,
                       site_longest_above_ischaemia_segment=segment)
    return figures


def guard_metrics(counts) -> dict:
    """The EPM guard's counts (the station's `epm.guard_counts`, GUARD_COUNTS) as metrics:
    epm_commands (the pose commands it received), epm_commands_raised (raised to the
    clearance floor), epm_commands_clamped (centre pulled into the workspace),
    epm_commands_rejected (not finite: the last safe command held)."""
    counts = np.asarray(counts, dtype=float).ravel()
    if counts.shape != (len(GUARD_COUNTS),):
        raise ValueError(f"epm.guard_counts has {counts.size} values, not {len(GUARD_COUNTS)} "
                         f"({', '.join(GUARD_COUNTS)})")
    return {"epm_commands" if name == "commands" else f"epm_commands_{name}": int(value)
            for name, value in zip(GUARD_COUNTS, counts)}


def run_metrics(colon, times, capsule_state, contact_load, epm_pose, *, capsule_radius,
                capsule_length, epm_geometry, start_s, sim_time, wall_time, stopped_early=None,
                diverged=False, epm_guard_counts=None, contact_pressure=None,
                wall_pressure=None):
    """Metrics of one run as a JSON-ready dict.

    Args:
        colon: the run's Colon (centerline and wall ground truth).
        times: (K,) log times (s).
        capsule_state: (13, K) capsule state log [quaternion wxyz, p_WC, w, v].
        contact_load: (K,) summed contact force magnitudes (N).
        epm_pose: (6, K) EPM log [p_WE, m_hat_W] (centre and moment direction).
        capsule_radius, capsule_length: capsule collision shape (m).
        epm_geometry: MagnetGeometry of the EPM (for its clearance to the skin).
        start_s: the scenario's start arc length (m).
        sim_time: simulated seconds.
        wall_time: seconds of wall-clock time the simulation took.
        stopped_early: None, or why the run ended before its duration.
        diverged: the run guard found the simulation no longer physical: the outcomes
            (OUTCOMES: how far the capsule got, its contact, its excursion) are null, since
            numbers from such a run mean nothing.
        epm_guard_counts: the station's `epm.guard_counts` at the end of the run, or None;
            given, its counts are reported (`guard_metrics`), whatever the run's status.
        contact_pressure: (K,) the contact's peak pressure (Pa; NaN for point contact), or
            None: the pressure metrics (`pressure_metrics`) are then null.
        wall_pressure: the run's map of the wall's patches (physics/wall_pressure.py
            `WallPressure`), or None: the per-site figures (`site_pressure_metrics`) are
            then null.

    Samples whose capsule state is not finite (or whose quaternion is far from unit length,
    as in a diverging run) are left out.
    """
    times, capsule_state = np.asarray(times), np.asarray(capsule_state)
    with np.errstate(all="ignore"):
        finite = (np.all(np.isfinite(capsule_state), axis=0)
                  & (np.abs(np.linalg.norm(capsule_state[:4], axis=0) - 1.0) < 0.5)
                  if capsule_state.size else np.zeros(len(times), dtype=bool))
    times, capsule_state = times[finite], capsule_state[:, finite]
    contact_load, epm_pose = np.asarray(contact_load)[finite], np.asarray(epm_pose)[:, finite]
    if contact_pressure is not None:
        contact_pressure = np.asarray(contact_pressure, dtype=float)[finite]
    timing = {"sim_time_s": float(sim_time), "wall_time_s": float(wall_time),
              "real_time_factor": sim_time / wall_time if wall_time > 0 else None,
              "colon_length_m": float(colon.centerline.s[-1]),
              "scenario_start_s_m": float(start_s), "stopped_early": stopped_early,
              "diverged": bool(diverged)}
    guarded = guard_metrics(epm_guard_counts) if epm_guard_counts is not None else {}
    sites = site_pressure_metrics(wall_pressure, colon.centerline)
    if len(times) == 0:
        sites.update({key: None for key in SITE_OUTCOMES})
        return {**timing, **{key: None for key in OUTCOMES}, "start_s_m": None,
                "min_epm_skin_gap_m": None, **sites, **guarded}
    R_WC, p_WC = capsule_poses(capsule_state)
    s, _, _ = colon.centerline.closest(p_WC)
    excursion = wall_excursion(colon, R_WC, p_WC, capsule_surface_points_C(capsule_radius,
                                                                           capsule_length))
    final_s = float(s[-1])

    gaps = [skin_gap(colon, epm_pose[:3, k], epm_pose[3:6, k], epm_geometry)
            for k in range(0, len(times), max(1, len(times) // 400))]
    distance = np.linalg.norm(epm_pose[:3].T - p_WC, axis=1)
    metrics = {
        "start_s_m": float(s[0]),
        "scenario_start_s_m": float(start_s),
        "final_s_m": final_s,
        "max_s_m": float(np.max(s)),
        "advance_m": final_s - float(s[0]),
        "stop_segment": colon.centerline.segment_at(final_s),
        "colon_length_m": float(colon.centerline.s[-1]),
        "sim_time_s": float(sim_time),
        "wall_time_s": float(wall_time),
        "real_time_factor": sim_time / wall_time if wall_time > 0 else None,
        "peak_contact_force_N": float(np.max(contact_load)) if len(contact_load) else 0.0,
        "max_wall_excursion_m": float(np.max(excursion)),
        "time_of_max_wall_excursion_s": float(times[int(np.argmax(excursion))]),
        "min_epm_skin_gap_m": float(np.min(gaps)),
        "min_epm_capsule_distance_m": float(np.min(distance)),
        **pressure_metrics(times, contact_pressure),
        **sites,
        "stopped_early": stopped_early,
        "diverged": bool(diverged),
    }
    metrics.update(guarded)
    if diverged:
        metrics.update({key: None for key in OUTCOMES + SITE_OUTCOMES})
    return metrics
