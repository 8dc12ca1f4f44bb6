"""The navigation benchmark: seeded random colons x navigators, one table.

A run puts the capsule in the rectum of one seeded random colon (`colon.seed`) and lets one
navigator drive the EPM for up to `duration` simulated seconds, stopping early when the
capsule reaches the cecum (its centreline station within `CECUM_MARGIN` of the end). The
suite runs in parallel processes on this machine (`engine="local"`) or on a Dask cluster
(`engine="dask"`: a local cluster of `workers` processes, or an existing scheduler's
address), with a progress line, and gives the same table for the same seeds either way.
A run whose process crashes, that outlives its wall-time limit (`run_timeout`), or that an
error ended (a plug-in's that raised or exited, naming it) is a row marked failed with its
reason (`status`, `error`), and the suite goes on; Ctrl-C and the termination signals stop
every run's processes (the run's worker and its camera's render process), keeping the runs
that finished.

Navigators, each a named scenario whose `epm.driver` drives the EPM (diagrams/default.yaml),
all run through the one run loop (app/run.py `simulate`, which seeds the random context):
- "autonomy-truth" (scenario Navigation), "autonomy-detected" (NavigationDetected): the
  lumen follower (navigation/autonomy.py), steering from the lumen truth or from the lumen
  tracker on the camera's frames, on the capsule's true pose;
- "autonomy-sensors" (NavigationSensors): the follower on what the capsule senses, the
  tracker's lumen and the magnetic localiser's pose estimate, with finite-size magnets;
- "teleop-guided", "teleop-unguided": the simulated operator at the haptic device
  (scenario Teleop), with and without the pseudo-force on the hand;
- "package.module:function": a user's navigator (`!Plugin`; the interface is in
  navigation/plugin.py) on the task's scenario (default Navigation).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection, wait
from pathlib import Path

import numpy as np

from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.population import patient_label
from capsule_drake.app.run import simulate
from capsule_drake.io.metrics import pressure_metrics, site_pressure_metrics
from capsule_drake.anatomy.lesions import SIZE_CLASSES
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.navigation.coverage import MucosaCoverage
from capsule_drake.navigation.lesions_seen import SEEN_SECONDS, LesionViews
from capsule_drake.navigation.plugin import load_navigator
from capsule_drake.physics.contact.tissue import TISSUE_COLUMNS
from capsule_drake.plugins import first_line, load_function, what_it_did
from capsule_drake.scenario import load_scenario

# A run reaches the cecum when the capsule's centreline station is this close to the end (m).
CECUM_MARGIN = 0.04
# Contact counts as wall contact above this load (N).
CONTACT_THRESHOLD = 0.05
# A run that ran its whole duration without reaching the cecum "stalled" when it got no
# closer than STALL_ADVANCE to its furthest point during the last STALL_WINDOW seconds;
# otherwise it was still advancing, and the time limit cut it off.
STALL_WINDOW = 30.0  # s
STALL_ADVANCE = 0.01  # m
# How often a run reports its progress to the suite (s of wall time).
PROGRESS_PERIOD = 1.0
# The Dask event topic the runs report their progress on.
PROGRESS_TOPIC = "capsule-benchmark-progress"
# The columns of the table, CSV and summary (per run; the summary averages or counts them).
# The patient's columns: the colon's length, the patient's traits, and the wall's tissue
# (physics/contact/tissue.py TISSUE_COLUMNS: how it was chosen, thickness, circumferential
# modulus, support, friction; NaN figures on the rigid stand-in, which has none).
COLUMNS = ("navigator", "seed", "colon_cm", "patient", *TISSUE_COLUMNS, "reached_cecum",
           "time_to_cecum_s", "progress",
           "progress_cm", "stuck_in", "wall_contact_s", "peak_contact_force_N",
           "peak_contact_pressure_kPa", "injury_pressure_s", "site_peak_pressure_kPa",
           "site_injury_s", "site_ischaemia_s", "centring_error_deg",
           "detection_error_pct", "detection_rate", "detection_fp_rate",
           "loc_pos_err_median_mm", "loc_pos_err_p95_mm", "loc_rot_err_median_deg",
           "epm_path_m", "coverage", "polyps_diminutive", "seen_diminutive", "polyps_small",
           "seen_small", "polyps_large", "seen_large", "polyps_detected", "polyp_fp_per_min",
           "diverticula", "seen_diverticula", "sim_time_s", "wall_time_s", "status", "error")
# A run's `status`: it finished (its row measures it, whatever ended it: the time limit, the
# cecum, the guard), or it failed (`error` says how: its process crashed, it outlived its
# wall-time limit, it raised or exited before it could simulate, or an error ended its
# simulation, naming the plug-in whose code raised or exited if one did).
FINISHED, FAILED = "finished", "failed"


# Built-in navigators: the named scenario each runs, and YAML laid over it.
NAVIGATORS = {
    "autonomy-truth": ("Navigation", ""),
    "autonomy-detected": ("NavigationDetected", ""),
    "autonomy-sensors": ("NavigationSensors", ""),
    "teleop-guided": ("Teleop", ""),
    "teleop-unguided": ("Teleop", "{pseudo_force: null}"),
}
BUILT_IN = tuple(NAVIGATORS)
# The benchmark's tiers: their colons (seeds) and the YAML that makes them. "standard": the
# ten procedural colons every earlier figure was measured on, distended and clean.
# "population": 30 patients drawn from the population model (anatomy/population.py; seeds
# 1000-1029, chosen before any run and never changed) with their lumen's state drawn too
# (residual fluid, segments not fully distended: anatomy/lumen_state.py), for rates with a
# meaningful interval; --seeds draws others.
TIERS = {"standard": ("0-9", ""),
         "population": ("1000-1029", "{colon: {source: !Population {}, lumen: {}}}")}


@dataclasses.dataclass(frozen=True)
class Task:
    """One run: a navigator (a named scenario and its driver) on a seeded colon."""

    navigator: str
    seed: int
    duration: float = 600.0
    # The scenario a user's navigator ("package.module:function") starts from, its driver
    # replaced by the plug-in; YAML laid over every navigator's scenario.
    scenario: str = "Navigation"
    scenario_text: str = ""
    # The tier's YAML (TIERS), laid under the task's own text.
    tier_text: str = ""
    log_period: float = 0.1
    # The scenario file the named scenarios come from (default diagrams/default.yaml).
    scenario_file: str | None = None
    # A user's polyp detector, "package.module:function" (navigation/lesions_seen.py),
    # scored on every frame; "": none.
    polyp_detector: str = ""


def task_scenario(task: Task):
    """The Scenario of a task: the navigator's scenario (or, for a user's navigator, the
    task's with `!Plugin`), the task's text, then its colon seed, duration and log period."""
    if task.navigator in NAVIGATORS:
        name, text = NAVIGATORS[task.navigator]
    else:
        load_navigator(task.navigator, f"one of {', '.join(BUILT_IN)}")
        name = task.scenario
        text = f"{{epm: {{driver: !Plugin {{factory: '{task.navigator}'}}}}}}"
    run = (f"{{duration: {task.duration!r}, colon: {{seed: {task.seed}}}, "
           f"outputs: {{log_period: {task.log_period!r}}}}}")
    return load_scenario(task.scenario_file, name,
                         [text, task.tier_text, task.scenario_text, run])


def run_task(task: Task, progress=None) -> dict:
    """Simulates one task through the run loop (`io.run.simulate`, which seeds the random
    context with the scenario's random_seed), stopping at the cecum; returns its row
    (COLUMNS) and its progress curve.

    progress: optional callable given a dict as the run goes: {"phase": "building"} at once,
    then about every PROGRESS_PERIOD s of wall time {"phase": "running", "t": simulated
    time (s), "duration", "s_cm": the capsule's centreline station (cm from the anal end),
    "segment": the colon segment it is in, "elapsed": wall time since the run began (s),
    "rate": simulated seconds per wall second since the simulation began}.
    """
    began = time.perf_counter()
    if progress is not None:
        progress({"phase": "building"})
    scenario = task_scenario(task)
    colon, _ = load_colon(scenario.colon)
    length = colon.centerline.length
    period = scenario.outputs.log_period
    extra = {}
    last_report, simulating_since = [-np.inf], [0.0]
    lesions = lesion_scene(scenario.colon)
    polyps, pouches = lesions.polyps, lesions.diverticula
    lesion_views, pouch_views = [], []

    def extend(builder, station):
        # Loaded as the run is built, so that the run names it if it breaks the run.
        detector = (load_function("polyp detector", task.polyp_detector, "a function")
                    if task.polyp_detector else None)
        if station.HasOutputPort("capsule.camera.rgb_image"):
            camera = station.GetSubsystemByName("capsule.camera")
            coverage = builder.AddNamedSystem("coverage", MucosaCoverage(
                colon, camera.lens, scenario.capsule.camera.far))
            for name in ("depth_image", "frame_info", "frame_pose"):
                builder.Connect(station.GetOutputPort(f"capsule.camera.{name}"),
                                coverage.GetInputPort(name))
            extra["coverage"] = LogVectorOutput(coverage.GetOutputPort("coverage"), builder, 1.0)
            for name in ("lumen_pixel", "lumen_visible", "far_pixel", "far_visible"):
                extra[name] = LogVectorOutput(station.GetOutputPort(f"capsule.lumen.{name}"),
                                              builder, period)
            extra["camera"] = camera
            labelled = station.HasOutputPort("capsule.camera.label_image")
            # The polyps (scored with a detector, if any) and the diverticula apart: a
            # polyp detector's mark on a diverticulum is a false positive.
            for name, mine, scorer, out in (("lesion_views", polyps, detector, lesion_views),
                                            ("diverticulum_views", pouches, None,
                                             pouch_views)):
                if not labelled or not (mine or scorer):
                    continue
                views = builder.AddNamedSystem(name, LesionViews(
                    {label: k for k, label in enumerate(lesion_labels(mine))}, len(mine),
                    int(camera.lens.pixel_rays()[1].sum()), camera.tick(),
                    camera.latency() + 1e-6, detector=scorer))
                for port in ("label_image", "depth_image", "frame_info") + (
                        ("rgb_image",) if scorer else ()):
                    builder.Connect(station.GetOutputPort(f"capsule.camera.{port}"),
                                    views.GetInputPort(port))
                out.append(views)
        if station.HasOutputPort("capsule.localizer.pose"):
            extra["localizer_pose"] = LogVectorOutput(
                station.GetOutputPort("capsule.localizer.pose"), builder, period)
        if station.HasOutputPort("capsule.lumen_tracker.lumen_pixel"):
            for name in ("lumen_pixel", "lumen_visible"):
                extra[f"tracker_{name}"] = LogVectorOutput(
                    station.GetOutputPort(f"capsule.lumen_tracker.{name}"), builder, period)

    def at_cecum(station, context):
        state = station.GetOutputPort("capsule.state").Eval(context)
        s = float(colon.centerline.closest(state[4:7])[0])
        now = time.perf_counter()
        if progress is not None and now - last_report[0] >= PROGRESS_PERIOD:
            if not np.isfinite(last_report[0]):
                simulating_since[0] = now
            last_report[0] = now
            t = float(context.get_time())
            progress({"phase": "running", "t": t, "duration": float(scenario.duration),
                      "s_cm": 100.0 * s, "segment": colon.centerline.segment_at(s),
                      "elapsed": now - began,
                      "rate": t / (now - simulating_since[0]) if t > 0 else 0.0})
        return "reached the cecum" if s >= length - CECUM_MARGIN else None

    result = simulate(scenario, progress=False, extend=extend, stop_when=at_cecum)
    s = colon.centerline.closest(result.capsule_state[4:7].T)[0]
    step = max(1, int(round(1.0 / period)))
    curve = (result.times[::step].tolist(), s[::step].tolist())
    # An error ended it (a plug-in's, or the simulation's), or the EPM came inside its
    # clearance (epm/clearance.py): the run did not do what it was asked.
    if result.status in ("error", "epm_clearance"):
        failed = failed_result(task, result.metrics["stopped_early"],
                               result.metrics.get("wall_time_s", np.nan))
        failed["row"]["sim_time_s"] = round(float(result.context.get_time()), 3)
        failed.update(curve=curve, segments=colon.centerline.segment_ranges(),
                      worker_pid=os.getpid())
        return failed
    camera = extra.pop("camera", None)
    data = {name: log.FindLog(result.context) for name, log in extra.items()}
    stopped = result.metrics.get("stopped_early")
    row = _metrics(task, colon, result, data, camera, stopped)
    if result.status == "diverged":  # nothing measured in such a run means anything
        row.update({key: np.nan for key in DIVERGED_NAN})
        row.update(reached_cecum=False, segments_passed=[])
    shown = (lesion_views[0].final_shown(lesion_views[0].GetMyContextFromRoot(result.context))
             if lesion_views else None)
    row.update(lesion_columns(polyps, shown))
    pouches_shown = (pouch_views[0].final_shown(pouch_views[0].GetMyContextFromRoot(
        result.context)) if pouch_views else None)
    row["diverticula"] = len(pouches)
    row["seen_diverticula"] = (0 if not pouches else np.nan if pouches_shown is None
                               else int(np.sum(pouches_shown >= SEEN_SECONDS)))
    score = (lesion_views[0].detector_score(None if shown is None else shown >= SEEN_SECONDS)
             if lesion_views and task.polyp_detector else None)
    row.update(polyps_detected=np.nan if score is None else score["seen_detected"],
               polyp_fp_per_min=np.nan if score is None else round(score["fp_per_min"], 2))
    row["patient"] = patient_label(scenario.colon)
    row.update(tissue_columns(result.metrics))
    row["sim_time_s"] = round(float(result.context.get_time()), 3)
    row["wall_time_s"] = round(float(result.metrics.get("wall_time_s", 0.0)), 1)
    row.update(status=FINISHED, error="")
    return {"row": row, "curve": curve, "segments": colon.centerline.segment_ranges(),
            "worker_pid": os.getpid()}


def tissue_columns(metrics: dict) -> dict:
    """The run's wall as its metrics give it (TISSUE_COLUMNS), NaN for a figure it has not
    got (the rigid stand-in's)."""
    return {key: np.nan if metrics.get(key) is None else metrics[key] for key in TISSUE_COLUMNS}


def lesion_columns(polyps, shown_s) -> dict:
    """Per size class, the polyps in the colon and those the run showed for at least
    SEEN_SECONDS (navigation/lesions_seen.py); NaN counts seen without a camera."""
    out = {}
    for size_class in SIZE_CLASSES:
        mine = [k for k, p in enumerate(polyps) if p.lesion.size_class == size_class]
        out[f"polyps_{size_class}"] = len(mine)
        out[f"seen_{size_class}"] = (np.nan if shown_s is None else
                                     int(sum(shown_s[k] >= SEEN_SECONDS for k in mine)))
    return out


def _rounded(value, digits: int) -> float:
    """`value` rounded, NaN for None (a measure the run has not got)."""
    return round(float(value), digits) if value is not None else np.nan


# The columns of a run the guard found diverged: not reported.
DIVERGED_NAN = ("time_to_cecum_s", "progress", "progress_cm", "wall_contact_s",
                "peak_contact_force_N", "peak_contact_pressure_kPa", "injury_pressure_s",
                "site_peak_pressure_kPa", "site_injury_s", "site_ischaemia_s",
                "centring_error_deg", "detection_error_pct",
                "detection_rate", "detection_fp_rate", "loc_pos_err_median_mm", "loc_pos_err_p95_mm",
                "loc_rot_err_median_deg", "coverage")


def _metrics(task, colon, result, data, camera, stopped) -> dict:
    length = colon.centerline.length
    times = result.times
    state = result.capsule_state
    s = colon.centerline.closest(state[4:7].T)[0]
    start_s = s[0] if len(s) else 0.0
    reached = np.flatnonzero(s >= length - CECUM_MARGIN)
    furthest = float(s.max()) if len(s) else 0.0
    load = result.contact_load
    pressure = pressure_metrics(times, result.contact_pressure)
    sites = site_pressure_metrics(result.wall_pressure, colon.centerline)
    dt = np.diff(times, append=times[-1]) if len(times) else np.zeros(0)
    epm = result.epm_pose[:3]
    centring = np.nan
    if camera is not None and "lumen_pixel" in data:
        pixel, visible = _logged_lumen(data, "lumen")
        if visible.any():
            rays = camera.lens.unproject(pixel[visible])
            angles = np.degrees(np.arccos(np.clip(rays[:, 2] / np.linalg.norm(rays, axis=1),
                                                  -1.0, 1.0)))
            centring = float(np.median(angles))
    detection_error, detection_rate, false_positives = _detection_scores(camera, data)
    localisation = _localisation_errors(data, state)
    coverage = float(data["coverage"].data()[0, -1]) if "coverage" in data and \
        data["coverage"].data().size else np.nan
    segments = colon.centerline.segment_ranges()
    stuck = "" if len(reached) else where_it_ended(
        times, s, colon.centerline.segment_at(furthest),
        cut_by_time=result.status == "completed")
    return {
        "navigator": task.navigator, "seed": task.seed,
        "colon_cm": round(float(100.0 * length), 1),
        "reached_cecum": bool(len(reached)),
        "time_to_cecum_s": round(float(times[reached[0]]), 2) if len(reached) else np.nan,
        "progress": round(float((furthest - start_s) / (length - start_s)), 4),
        "progress_cm": round(float(100.0 * (furthest - start_s)), 1),
        "stuck_in": stopped or stuck,
        "wall_contact_s": round(float(np.sum(dt[load > CONTACT_THRESHOLD])), 2),
        "peak_contact_force_N": round(float(load.max()) if load.size else 0.0, 3),
        # The contact's peak pressure and the seconds above the injury threshold
        # (physics/tissue.py); NaN for point contact, which has no pressure.
        "peak_contact_pressure_kPa": _rounded(pressure["peak_contact_pressure_kPa"], 1),
        "injury_pressure_s": _rounded(pressure["time_above_injury_pressure_s"], 2),
        # Per patch of the wall (physics/wall_pressure.py): the highest pressure one felt
        # and the longest time ONE patch spent above 330 kPa and above 4.0 kPa; NaN without
        # a pressure field.
        "site_peak_pressure_kPa": _rounded(sites.get("site_peak_pressure_kPa"), 1),
        "site_injury_s": _rounded(sites.get("site_longest_above_injury_s"), 2),
        "site_ischaemia_s": _rounded(sites.get("site_longest_above_ischaemia_s"), 2),
        "centring_error_deg": round(centring, 1) if np.isfinite(centring) else np.nan,
        "detection_error_pct": (round(detection_error, 2) if np.isfinite(detection_error)
                                else np.nan),
        "detection_rate": round(detection_rate, 3) if np.isfinite(detection_rate) else np.nan,
        "detection_fp_rate": (round(false_positives, 3) if np.isfinite(false_positives)
                              else np.nan),
        **localisation,
        "epm_path_m": round(float(np.sum(np.linalg.norm(np.diff(epm, axis=1), axis=0))), 3),
        "coverage": round(coverage, 4) if np.isfinite(coverage) else np.nan,
        # Through each segment; the cecum, a blind end, counts when the run reached it.
        "segments_passed": [name for name, (_, end) in segments.items()
                            if furthest >= end or (name == list(segments)[-1] and len(reached))],
    }


def where_it_ended(times, s, segment: str, cut_by_time: bool) -> str:
    """The `stuck_in` of a run that did not reach the cecum and was not stopped early:
    `segment` (where its furthest point is) if it stalled, i.e. it came no closer than
    STALL_ADVANCE to that point during the last STALL_WINDOW s; "time limit (<segment>, at
    <station> cm)" if it was still advancing when the time limit (`cut_by_time`) ended it.

    times (s) and s (m, centreline stations) are the run's log.
    """
    times, s = np.asarray(times, dtype=float), np.asarray(s, dtype=float)
    if not len(s):
        return segment
    furthest = float(s.max())
    got_there = float(times[np.argmax(s >= furthest - STALL_ADVANCE)])
    if cut_by_time and times[-1] - got_there < STALL_WINDOW:
        return f"time limit ({segment}, at {100.0 * furthest:.0f} cm)"
    return segment


def _logged_lumen(data, prefix: str):
    """The logged `<prefix>_pixel` samples (N, 2) and whether each saw the lumen (N,)."""
    pixel = data[f"{prefix}_pixel"].data().T
    visible = (data[f"{prefix}_visible"].data()[0] > 0.5) & np.all(np.isfinite(pixel), axis=1)
    return pixel, visible


def localisation_errors(estimate, truth) -> tuple[np.ndarray, np.ndarray]:
    """Per sample, the estimated pose's position error (m) and orientation error (rad, the
    angle of the rotation between them), for poses [q wxyz, p] as rows of (N, 7) arrays."""
    estimate, truth = np.asarray(estimate, dtype=float), np.asarray(truth, dtype=float)
    position = np.linalg.norm(estimate[:, 4:7] - truth[:, 4:7], axis=1)
    q1 = estimate[:, :4] / np.linalg.norm(estimate[:, :4], axis=1, keepdims=True)
    q2 = truth[:, :4] / np.linalg.norm(truth[:, :4], axis=1, keepdims=True)
    angle = 2.0 * np.arccos(np.clip(np.abs(np.sum(q1 * q2, axis=1)), 0.0, 1.0))
    return position, angle


def _localisation_errors(data, state) -> dict:
    """The run's localiser against the truth, sample by sample: median and 95th percentile
    of the position error (mm), median orientation error (deg). NaN without a localiser."""
    keys = ("loc_pos_err_median_mm", "loc_pos_err_p95_mm", "loc_rot_err_median_deg")
    if "localizer_pose" not in data:
        return dict.fromkeys(keys, np.nan)
    estimate = data["localizer_pose"].data().T
    truth = np.asarray(state).T[:, :7]
    count = min(len(estimate), len(truth))
    if count == 0:
        return dict.fromkeys(keys, np.nan)
    position, angle = localisation_errors(estimate[:count], truth[:count])
    ok = np.isfinite(position) & np.isfinite(angle)
    if not ok.any():
        return dict.fromkeys(keys, np.nan)
    return dict(zip(keys, (round(1000.0 * float(np.median(position[ok])), 2),
                           round(1000.0 * float(np.percentile(position[ok], 95)), 2),
                           round(float(np.degrees(np.median(angle[ok]))), 2))))


def _detection_scores(camera, data) -> tuple[float, float, float]:
    """How the run's lumen tracker did against the image-side truth (perception/
    lumen_truth.py, `far_region` of each frame's range image), sampled together: the median
    distance between detected and true pixel (% of the image diagonal) where both see the
    lumen, the share of lumen-in-view samples the tracker reported visible, and the share of
    samples without a lumen in view that it reported visible (false positives). NaN for a run
    without a tracker (or a measure with no samples). Tracker and truth both hold the last
    frame's result; they may be a frame apart for the tracker's reading delay."""
    if camera is None or "tracker_lumen_pixel" not in data or "far_pixel" not in data:
        return np.nan, np.nan, np.nan
    truth, truth_visible = _logged_lumen(data, "far")
    found, found_visible = _logged_lumen(data, "tracker_lumen")
    count = min(len(truth), len(found))
    truth, truth_visible = truth[:count], truth_visible[:count]
    found, found_visible = found[:count], found_visible[:count]
    false_positives = (float(found_visible[~truth_visible].mean()) if (~truth_visible).any()
                       else np.nan)
    if not truth_visible.any():
        return np.nan, np.nan, false_positives
    rate = float(found_visible[truth_visible].mean())
    both = truth_visible & found_visible
    if not both.any():
        return np.nan, rate, false_positives
    diagonal = float(np.hypot(camera.lens.width, camera.lens.height))
    error = 100.0 * float(np.median(np.linalg.norm(found[both] - truth[both], axis=1))) / diagonal
    return error, rate, false_positives


def default_run_timeout(duration: float) -> float:
    """The wall-time limit of a run of `duration` simulated seconds (s): three times the
    duration plus five minutes. The slowest navigator (the simulated operator with the arm)
    simulates about a second per wall second with two runs on two cores, and starting
    Python and Drake, building the station and a cold colon cache take up to a minute."""
    return 300.0 + 3.0 * float(duration)


class EngineError(Exception):
    """The suite's engine could not be used (a Dask scheduler that cannot be reached, an
    address that is not one); nothing was run."""


def failed_result(task: Task, error: str, wall_time: float = np.nan) -> dict:
    """The result of a run that failed (its process crashed, it timed out, it raised or
    exited before simulating, or an error ended its simulation): its row has the navigator
    and seed, `status` FAILED, the reason in `error`, the wall time it took, and nothing
    measured."""
    row = dict.fromkeys(COLUMNS, np.nan)
    row.update(navigator=task.navigator, seed=task.seed, reached_cecum=False, stuck_in="",
               wall_time_s=round(float(wall_time), 1), status=FAILED, error=error,
               segments_passed=[])
    return {"row": row, "curve": ([], []), "segments": {}, "worker_pid": None}


class NotedSignals:
    """Within the block, SIGINT, SIGTERM and SIGHUP are noted, not raised, where their
    handler is Python's (Ctrl-C's KeyboardInterrupt, the command line's `Interrupted`), and
    each wakes `wakeup` (a connection to wait on); leaving it puts the handlers back.
    `raise_noted()` then raises the first one as its handler would have. So what the block
    does (stopping the workers, writing a row or the outputs) is never cut off halfway.
    Outside the main thread, or for a signal left to the system, nothing changes."""

    NAMES = ("SIGINT", "SIGTERM", "SIGHUP")

    def __init__(self):
        self.noted: int | None = None
        self._previous: dict[int, object] = {}
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self.wakeup = Connection(self._read, writable=False)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for name in self.NAMES:
                number = getattr(signal, name, None)
                handler = signal.getsignal(number) if number is not None else None
                if callable(handler):
                    self._previous[number] = handler
                    signal.signal(number, self._note)
        return self

    def _note(self, number, frame):
        if self.noted is None:
            self.noted = number
        try:
            os.write(self._write, b"!")
        except OSError:  # the pipe is full: it is awake already
            pass

    def __exit__(self, *exc):
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self.wakeup.close()
        os.close(self._write)
        return False

    def raise_noted(self) -> None:
        if self.noted is not None and self.noted in self._previous:
            self._previous[self.noted](self.noted, None)  # raises


# The program a run's process starts with. Before anything else (importing Drake takes
# seconds), it asks Linux to kill it when the suite's process dies, however that dies (kill
# -9 too), and ends at once if the suite has already gone; elsewhere a thread watches the
# parent (`_worker_main`). Its arguments: the suite's pid, the fd of the pipe it reports on.
_WORKER_PROGRAM = """\
import ctypes, os, signal, sys
parent = int(sys.argv[1])
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PDEATHSIG
except (OSError, AttributeError):
    pass
if os.getppid() != parent:
    os._exit(1)
from capsule_drake.app.benchmark import _worker_main
_worker_main(parent, int(sys.argv[2]))
"""

# How long a run's process may take to exit once it has reported its result or closed its
# pipe (the camera's render process is stopped in that time), before it is killed (s).
EXIT_GRACE = 10.0


def _worker_main(parent: int, fd: int) -> None:
    """A run's process: reads its Task pickled from stdin, runs it, and sends on the pipe
    `fd` ("progress", info) as it goes, then ("result", result) or ("error", reason)."""
    channel = Connection(fd, readable=False)

    def watch():  # where the kernel cannot be asked to (not Linux)
        while True:
            time.sleep(1.0)
            if os.getppid() != parent:
                os.killpg(0, signal.SIGKILL)  # this run's process group: the camera's too

    threading.Thread(target=watch, daemon=True).start()
    task = pickle.loads(sys.stdin.buffer.read())
    try:
        result = run_task(task, progress=lambda info: channel.send(("progress", info)))
    except BaseException as e:  # the run failed before it simulated (its station, a plug-in)
        channel.send(("error", what_it_did(e)))
    else:
        channel.send(("result", result))
    channel.close()


def _exit_description(returncode: int) -> str:
    if returncode < 0:
        try:
            name = f" ({signal.Signals(-returncode).name})"
        except ValueError:
            name = ""
        return f"signal {-returncode}{name}"
    return f"status {returncode}"


def _run_environment(threads: int) -> dict:
    """The environment of a run's process: this one's, with the suite's import path, and the
    numerical libraries' thread pools sized to its share of the cores (`threads`) unless the
    user has sized them. Each run's OpenBLAS otherwise starts a thread per core, and runs
    side by side on a 2-core machine spend ~3x as long spinning on one another (measured: a
    population colon's build, two at a time, 105-119 s against 30-43 s)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(name, str(threads))
    return env


class _RunProcess:
    """One run in a process of its own, the leader of a process group of its own (so the
    camera's render process, its child, is in it too, and a Ctrl-C at the terminal reaches
    the suite alone): started at once, then polled by the suite."""

    def __init__(self, task: Task, threads: int = 1):
        self.task = task
        self.started = time.monotonic()
        self.result: dict | None = None
        self.closed = False           # its pipe has closed
        self.done_at: float | None = None  # when it reported its result or closed its pipe
        read, write = os.pipe()
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", _WORKER_PROGRAM, str(os.getpid()), str(write)],
                stdin=subprocess.PIPE, pass_fds=(write,), process_group=0,
                env=_run_environment(threads))
        except BaseException:
            os.close(read)
            raise
        finally:
            os.close(write)
        self.channel = Connection(read, writable=False)
        try:
            self.process.stdin.write(pickle.dumps(task))
            self.process.stdin.close()
        except OSError:  # it has died already: its pipe says so
            pass

    @property
    def wall_time(self) -> float:
        return time.monotonic() - self.started

    def receive(self, on_progress) -> bool:
        """Takes in what the run has sent so far; True when that includes its result."""
        had = self.result is not None
        try:
            while not self.closed and self.channel.poll():
                kind, value = self.channel.recv()
                if kind == "progress":
                    on_progress(value)
                elif kind == "result":
                    self.result = value
                else:
                    self.result = failed_result(self.task, value, self.wall_time)
        except (EOFError, OSError):  # the process has ended, or is ending
            self.closed = True
        if (self.closed or self.result is not None) and self.done_at is None:
            self.done_at = time.monotonic()
        return self.result is not None and not had

    def exited(self) -> bool:
        """Whether the process has ended (not reaped: its pid, and so the id of its process
        group, stays taken until `stop()`)."""
        if not hasattr(os, "waitid"):
            return self.process.poll() is not None
        try:
            return os.waitid(os.P_PID, self.process.pid,
                             os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
        except ChildProcessError:
            return True

    def stop(self) -> int:
        """Kills what is left of the run's process group, reaps the process and returns
        its exit status."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.process.wait()
        self.channel.close()
        return self.process.returncode


def _run_local(tasks, workers, display, finish, run_timeout):
    """A process for every run (a worker that ran one after another kept 0.6-0.7 GB more
    after each, 13.9 GB after 23 runs, until two of them filled the machine's 24 GB; a
    run's memory goes back to the system when it ends), `workers` at a time."""
    waiting = list(enumerate(tasks))[::-1]
    running: dict[int, _RunProcess] = {}
    threads = max(1, (os.cpu_count() or 1) // max(workers, 1))
    with NotedSignals() as signals:
        try:
            while (waiting or running) and signals.noted is None:
                while waiting and len(running) < workers:
                    k, task = waiting.pop()
                    running[k] = _RunProcess(task, threads)
                timeout = 1.0
                for run in running.values():
                    if run.done_at is not None:  # waiting for its process to exit
                        timeout = min(timeout, 0.05)
                    elif run_timeout is not None:
                        timeout = min(timeout, run.started + run_timeout - time.monotonic())
                wait([run.channel for run in running.values() if not run.closed]
                     + [signals.wakeup], timeout=max(0.0, timeout))
                for k, run in list(running.items()):
                    if run.receive(lambda info, k=k: display.update(k, info)):
                        finish(k, run.result)  # its row at once, while its process exits
                    if run.done_at is None:
                        if run_timeout is not None and run.wall_time > run_timeout:
                            run.stop()
                            del running[k]
                            finish(k, failed_result(
                                run.task, f"timed out after {run_timeout:g} s", run.wall_time))
                    elif run.exited() or time.monotonic() - run.done_at > EXIT_GRACE:
                        status = run.stop()
                        del running[k]
                        if run.result is None:
                            finish(k, failed_result(
                                run.task, "crashed: worker exited with "
                                f"{_exit_description(status)}", run.wall_time))
        finally:
            for run in running.values():
                run.stop()
    signals.raise_noted()


def _run_task_reporting_to_dask(task: Task, key: int) -> dict:
    """run_task on a Dask worker, its progress sent as events on PROGRESS_TOPIC (through
    the scheduler, so a worker on another machine reports the same way). A run that raises
    or exits before it simulates is a failed result here: a SystemExit (a plug-in's
    sys.exit()) would take the worker down with it."""
    from distributed import get_worker
    worker = get_worker()
    began = time.monotonic()
    try:
        return run_task(task, progress=lambda info: worker.log_event(
            PROGRESS_TOPIC, {"key": key, **info}))
    except BaseException as e:
        return failed_result(task, what_it_did(e), time.monotonic() - began)


def run_suite(tasks: list[Task], workers: int = 2, engine: str = "local",
              address: str | None = None, progress: bool = True,
              on_result=None, stream=None, line_period: float = 10.0,
              run_timeout: float | None = None) -> list[dict]:
    """Runs the tasks in parallel; returns their results in the tasks' order.

    engine "local": a process of its own for each run, `workers` at a time, on this
    machine. "dask": a Dask cluster, `address` of an existing scheduler or else a local
    cluster of `workers` processes (EngineError when it cannot be reached).
    run_timeout: the wall-time limit of a run (s; None: none), from its process's start
    (local) or its first report (Dask).
    A run that crashes its process, outlives its limit, raises or exits before it simulates,
    or that an error ends gives a result of status FAILED (`failed_result`: `error` says
    why), and the others go on.
    on_result: called with each result as its run finishes (e.g. `RowWriter`), so a long
    suite that is interrupted keeps the runs it finished. Ctrl-C or a termination signal
    (where Python handles it) kills every run's processes, then is raised.
    progress: show each run's progress on `stream` (default stderr) as it goes
    (`RunsProgress`; `line_period`: seconds between two lines of one run when the stream is
    not a terminal). The runs report it on their result pipes (local) or Dask events.
    """
    if engine not in ("local", "dask"):
        raise ValueError(f"benchmark engine {engine!r} is not 'local' or 'dask'")
    display = RunsProgress(tasks, progress, stream=stream, line_period=line_period)
    display.starting(workers if engine == "local" or address is None else None, engine)
    results: list[dict | None] = [None] * len(tasks)

    def finish(k, result):
        results[k] = result
        if on_result is not None:
            on_result(result)
        display.finished(k, result)

    try:
        if engine == "local":
            _run_local(tasks, workers, display, finish, run_timeout)
        else:
            _run_dask(tasks, workers, address, display, finish, run_timeout)
    finally:
        display.close()
    return results


def _run_dask(tasks, workers, address, display, finish, run_timeout):
    from dask.distributed import Client, LocalCluster, wait as wait_for
    from distributed import KilledWorker
    import dask
    cluster = None
    if address is None:
        # This machine only: the scheduler and workers would run whatever they are sent. A
        # run whose worker dies is not tried again (it would crash the next one too).
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, host="127.0.0.1")
    try:
        try:
            client = Client(address or cluster)
        except (OSError, ValueError, TypeError) as e:  # OSError: a timeout too
            if cluster is not None:
                raise
            raise EngineError(f"cannot reach a Dask scheduler at {address!r} "
                              f"({first_line(e)})") from None
        with client:
            started: dict[int, float] = {}

            def report(event):
                info = event[1]
                started.setdefault(info["key"], time.monotonic())
                display.update(info["key"], info)

            client.subscribe_topic(PROGRESS_TOPIC, report)
            futures = {client.submit(_run_task_reporting_to_dask, task, k, pure=False): k
                       for k, task in enumerate(tasks)}
            while futures:
                try:
                    done, _ = wait_for(list(futures), timeout=1.0,
                                       return_when="FIRST_COMPLETED")
                except TimeoutError:  # none finished within the second
                    done = ()
                for future in done:
                    k = futures.pop(future)
                    if future.status == "finished":
                        finish(k, future.result())
                        continue
                    error = future.exception()
                    reason = ("crashed: the Dask worker running it died"
                              if isinstance(error, KilledWorker) else what_it_did(error))
                    finish(k, failed_result(tasks[k], reason,
                                            time.monotonic() - started.get(k, np.nan)))
                if run_timeout is not None:
                    for future, k in list(futures.items()):
                        if k in started and time.monotonic() - started[k] > run_timeout:
                            # Dask cannot stop a task's thread: the scheduler forgets it,
                            # and a local cluster's worker goes as the cluster closes.
                            future.cancel()
                            del futures[future]
                            finish(k, failed_result(tasks[k],
                                                    f"timed out after {run_timeout:g} s",
                                                    time.monotonic() - started[k]))
            client.unsubscribe_topic(PROGRESS_TOPIC)
    finally:
        if cluster is not None:
            cluster.close()


class RunsProgress:
    """Each run's progress on stderr while a suite goes: per run, its simulated time and
    where the capsule is (colon segment, centreline station in cm from the anal end); a line
    per finished run with how it ended.

    On a terminal, a block of one line per running run under a bar of the runs done, redrawn
    in place; otherwise (a log file, a pipe) plain lines: a run's start, then its progress
    every `line_period` s of wall time, then its end. Thread-safe (updates arrive from a
    queue-draining thread or Dask's event loop).
    """

    def __init__(self, tasks, enabled: bool = True, stream=None, line_period: float = 10.0):
        self.tasks, self.enabled = tasks, enabled
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.line_period = line_period
        self.start = time.perf_counter()
        self.running: dict[int, dict] = {}
        self.last_line: dict[int, float] = {}
        self.done = 0
        self._drawn = 0
        self._last_draw = -np.inf
        self._shown_running: set[int] = set()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        if self.enabled and self.tty:  # the clock and bar move even while no run reports
            threading.Thread(target=self._heartbeat, daemon=True).start()

    def _heartbeat(self) -> None:
        while not self._closed.wait(1.0):
            with self._lock:
                if not self._closed.is_set():
                    self._draw()

    def _name(self, k) -> str:
        return f"{self.tasks[k].navigator} seed {self.tasks[k].seed}"

    def _clock(self) -> str:
        return f"[{time.perf_counter() - self.start:6.0f} s]"

    def starting(self, workers, engine: str) -> None:
        """The suite's first line, at once (a worker process takes a few seconds to start
        Python and Drake before its first run reports)."""
        if not self.enabled:
            return
        where = (f"{workers} local worker processes" if engine == "local" else
                 f"a local Dask cluster of {workers} processes" if workers else
                 "the Dask scheduler's workers")
        line = (f"{len(self.tasks)} runs on {where}; each reports once its process has "
                "started Python and Drake")
        with self._lock:
            if self.tty:
                self._write(line + "\n")
                self._draw()
            else:
                self._write(f"{self._clock()} {line}\n")

    def describe(self, k, info) -> str:
        if info.get("phase") != "running":
            return f"{self._name(k)}: building the station"
        rate = info.get("rate", 0.0)
        return (f"{self._name(k)}: {info['t']:6.1f} / {info['duration']:g} s simulated, "
                f"{info['segment']} at {info['s_cm']:.0f} cm"
                + (f" (x{rate:.2f} real time)" if rate > 0 else ""))

    def update(self, k, info: dict) -> None:
        if not self.enabled:
            return
        with self._lock:
            if k not in self.running and self.last_line.get(k) == np.inf:
                return  # a late report of a run that has finished
            self.running[k] = info
            now = time.perf_counter()
            if self.tty:
                if now - self._last_draw >= 0.2:
                    self._draw()
            elif (k not in self.last_line or info.get("phase") == "building"
                  or k not in self._shown_running
                  or now - self.last_line[k] >= self.line_period):
                self.last_line[k] = now
                if info.get("phase") == "running":
                    self._shown_running.add(k)
                self._write(f"{self._clock()} {self.describe(k, info)}\n")

    def finished(self, k, result: dict) -> None:
        with self._lock:
            self.done += 1
            self.running.pop(k, None)
            self.last_line[k] = np.inf
            if not self.enabled:
                return
            row = result["row"]
            line = f"{self._clock()} done {self.done}/{len(self.tasks)}: {self._name(k)}: "
            if row.get("status") == FAILED:
                line += f"failed: {row['error']}"
            else:
                ending = (f"reached the cecum at {row['time_to_cecum_s']:.1f} s"
                          if row["reached_cecum"] else f"ended: {row['stuck_in']}")
                line += (f"{ending}; {row['sim_time_s']:.1f} s simulated in "
                         f"{row['wall_time_s']:.0f} s")
            if self.tty:
                self._clear()
                self._write(line + "\n")
                self._draw()
            else:
                self._write(line + "\n")

    def close(self) -> None:
        with self._lock:
            self._closed.set()
            if self.enabled and self.tty:
                self._clear()

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()

    def _clear(self) -> None:
        if self._drawn:
            self._write(f"\x1b[{self._drawn}F\x1b[J")
            self._drawn = 0

    def _draw(self) -> None:
        width = max(20, shutil.get_terminal_size((100, 20)).columns - 1)
        total = len(self.tasks)
        bar = "#" * int(30 * self.done / max(total, 1))
        lines = [f"[{bar:<30}] {self.done}/{total} runs  "
                 f"{time.perf_counter() - self.start:6.0f} s"]
        lines += [f"  {self.describe(k, info)}" for k, info in sorted(self.running.items())]
        self._clear()
        self._write("".join(line[:width] + "\n" for line in lines))
        self._drawn = len(lines)
        self._last_draw = time.perf_counter()


def _json_default(value):
    """numpy scalars and arrays in results as plain JSON."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


class RowWriter:
    """Appends each finished run's row to a CSV file at once (header first)."""

    def __init__(self, path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "w", newline="") as f:
            csv.DictWriter(f, fieldnames=COLUMNS).writeheader()

    def __call__(self, result: dict) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore").writerow(result["row"])


def wilson_interval(successes: int, runs: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval (95 % by default) of a rate of successes in runs: unlike
    the normal approximation it stays inside [0, 1] and is not empty at 0/n or n/n."""
    if runs == 0:
        return 0.0, 1.0
    p = successes / runs
    centre = (p + z * z / (2 * runs)) / (1 + z * z / runs)
    half = z / (1 + z * z / runs) * np.sqrt(p * (1 - p) / runs + z * z / (4 * runs * runs))
    return max(0.0, centre - half), min(1.0, centre + half)


def summary(results: list[dict]) -> list[dict]:
    """Per navigator: runs, cecal intubation rate with its 95 % Wilson interval, mean time
    to cecum (of those that reached it), mean progress, and the means of the other columns;
    for the localisation errors, the worst run's too."""
    out = []
    for navigator in dict.fromkeys(r["row"]["navigator"] for r in results):
        rows = [r["row"] for r in results if r["row"]["navigator"] == navigator]

        def finite(key):
            values = np.array([row.get(key, np.nan) for row in rows], dtype=float)
            return values[np.isfinite(values)]

        def mean(key):
            values = finite(key)
            return round(float(values.mean()), 3) if len(values) else np.nan

        def worst(key):
            values = finite(key)
            return round(float(values.max()), 3) if len(values) else np.nan

        out.append({"navigator": navigator, "runs": len(rows),
                    "reached_cecum": f"{sum(row['reached_cecum'] for row in rows)}/{len(rows)}",
                    "cecum_95ci": "[{:.2f}, {:.2f}]".format(*wilson_interval(
                        sum(bool(row["reached_cecum"]) for row in rows), len(rows))),
                    "colon_cm": mean("colon_cm"),
                    "time_to_cecum_s": mean("time_to_cecum_s"), "progress": mean("progress"),
                    "wall_contact_s": mean("wall_contact_s"),
                    "peak_contact_force_N": mean("peak_contact_force_N"),
                    "peak_contact_pressure_kPa": mean("peak_contact_pressure_kPa"),
                    "injury_pressure_s": mean("injury_pressure_s"),
                    "site_peak_pressure_kPa": mean("site_peak_pressure_kPa"),
                    "site_injury_s": mean("site_injury_s"),
                    "site_ischaemia_s": mean("site_ischaemia_s"),
                    "centring_error_deg": mean("centring_error_deg"),
                    "detection_error_pct": mean("detection_error_pct"),
                    "detection_rate": mean("detection_rate"),
                    "detection_fp_rate": mean("detection_fp_rate"),
                    **{f"{key}{suffix}": how(key)
                       for key in ("loc_pos_err_median_mm", "loc_pos_err_p95_mm",
                                   "loc_rot_err_median_deg")
                       for suffix, how in (("", mean), ("_worst", worst))},
                    "epm_path_m": mean("epm_path_m"), "coverage": mean("coverage"),
                    **{f"seen_{size_class}": _seen(rows, size_class)
                       for size_class in SIZE_CLASSES},
                    "seen_diverticula": _seen(rows, "diverticula"),
                    "polyp_sensitivity": _sensitivity(rows),
                    "polyp_fp_per_min": mean("polyp_fp_per_min")})
    return out


def _sensitivity(rows) -> str:
    """"detected/seen" polyps over the runs that scored a polyp detector ("-": none)."""
    scored = [row for row in rows if np.isfinite(float(row.get("polyps_detected", np.nan)))]
    seen = sum(int(row[f"seen_{c}"]) for row in scored for c in SIZE_CLASSES
               if np.isfinite(float(row[f"seen_{c}"])))
    if not scored:
        return "-"
    return f"{sum(int(row['polyps_detected']) for row in scored)}/{seen}"


def _seen(rows, size_class: str) -> str:
    """"seen/present" polyps of a size class (or "diverticula") over the runs that counted
    them ("-": none)."""
    counted = [row for row in rows
               if np.isfinite(float(row.get(f"seen_{size_class}", np.nan)))]
    present = sum(int(row[f"polyps_{size_class}" if size_class in SIZE_CLASSES
                          else size_class]) for row in counted)
    if not present:
        return "-"
    return f"{sum(int(row[f'seen_{size_class}']) for row in counted)}/{present}"


def breakdown(results: list[dict]) -> list[dict]:
    """Per navigator, the cecal intubation rate (with its Wilson interval) and the mean time
    to the cecum of each group of the population's patients: by sigmoid variant, by sex and
    by tercile of the colon's length (the terciles of the runs' own colons). Empty when no
    run's colon was drawn from the population (its `patient` is "")."""
    rows = [r["row"] for r in results]

    def patient(row) -> str:   # a failed run's row has no patient (NaN)
        value = row.get("patient")
        return value if isinstance(value, str) else ""

    if not any(patient(row) for row in rows):
        return []
    lengths = np.array([row.get("colon_cm", np.nan) for row in rows], dtype=float)
    cuts = np.nanquantile(lengths, [1 / 3, 2 / 3])
    groups = {
        "all": lambda row: True,
        "normal sigmoid": lambda row: "normal sigmoid" in patient(row),
        "redundant sigmoid": lambda row: "redundant sigmoid" in patient(row),
        "female": lambda row: patient(row).startswith("female"),
        "male": lambda row: patient(row).startswith("male"),
        f"length < {cuts[0]:.0f} cm": lambda row: row.get("colon_cm", np.nan) < cuts[0],
        f"length {cuts[0]:.0f}-{cuts[1]:.0f} cm":
            lambda row: cuts[0] <= row.get("colon_cm", np.nan) < cuts[1],
        f"length >= {cuts[1]:.0f} cm": lambda row: row.get("colon_cm", np.nan) >= cuts[1],
    }
    out = []
    for navigator in dict.fromkeys(row["navigator"] for row in rows):
        mine = [row for row in rows if row["navigator"] == navigator]
        for group, member in groups.items():
            chosen = [row for row in mine if member(row)]
            if not chosen:
                continue
            reached = sum(bool(row["reached_cecum"]) for row in chosen)
            times = np.array([row.get("time_to_cecum_s", np.nan) for row in chosen],
                             dtype=float)
            times = times[np.isfinite(times)]
            out.append({"navigator": navigator, "group": group,
                        "reached_cecum": f"{reached}/{len(chosen)}",
                        "cecum_95ci": "[{:.2f}, {:.2f}]".format(
                            *wilson_interval(reached, len(chosen))),
                        "time_to_cecum_s": round(float(times.mean()), 1) if len(times)
                        else np.nan})
    return out


def segment_table(results: list[dict]) -> list[dict]:
    """Per navigator, the share of runs that got through each colon segment."""
    names = _segment_names(results)
    out = []
    for navigator in dict.fromkeys(r["row"]["navigator"] for r in results):
        rows = [r["row"] for r in results if r["row"]["navigator"] == navigator]
        out.append({"navigator": navigator, **{
            name: f"{sum(name in row['segments_passed'] for row in rows)}/{len(rows)}"
            for name in names}})
    return out


def _segment_names(results: list[dict]) -> list[str]:
    """The colon's segments, from the first run that finished (a failed run has none)."""
    return next((list(r["segments"]) for r in results if r.get("segments")), [])


def format_table(rows: list[dict], columns) -> str:
    cells = [[str(row.get(c, "")) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[k]) for r in cells)) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def write_outputs(results: list[dict], out_dir: Path) -> dict[str, Path]:
    """runs.csv (one row per run), summary.csv, progress.png (progress against time) and
    segments.png (share of runs through each colon segment, per navigator)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"runs": out_dir / "runs.csv", "summary": out_dir / "summary.csv",
             "progress": out_dir / "progress.png", "segments": out_dir / "segments.png",
             "results": out_dir / "results.json"}
    # Everything the table and plots are made from (rows, progress curves, segments), so
    # they can be redrawn or analysed further without rerunning the suite.
    with open(paths["results"], "w") as f:
        json.dump(results, f, default=_json_default)
    with open(paths["runs"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for r in results:
            writer.writerow(r["row"])
    rows = summary(results)
    with open(paths["summary"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    groups = breakdown(results)
    if groups:
        paths["breakdown"] = out_dir / "breakdown.csv"
        with open(paths["breakdown"], "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(groups[0]))
            writer.writeheader()
            writer.writerows(groups)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    navigators = list(dict.fromkeys(r["row"]["navigator"] for r in results))
    colours = {n: plt.cm.tab10(k % 10) for k, n in enumerate(navigators)}
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in results:
        t, s = r["curve"]
        navigator = r["row"]["navigator"]
        ax.plot(t, 100.0 * np.asarray(s), color=colours[navigator], lw=1.0, alpha=0.8)
    for n in navigators:
        ax.plot([], [], color=colours[n], label=n)
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("centreline station of the capsule (cm)")
    ax.set_title("progress toward the cecum, one line per run")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(paths["progress"], dpi=120)
    plt.close(fig)
    names = _segment_names(results)
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(navigators), 1)
    for k, n in enumerate(navigators):
        rows = [r["row"] for r in results if r["row"]["navigator"] == n]
        share = [np.mean([name in row["segments_passed"] for row in rows]) for name in names]
        ax.bar(np.arange(len(names)) + k * width, share, width, color=colours[n], label=n)
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=20, fontsize=8)
    ax.set_ylabel("share of runs through the segment")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(paths["segments"], dpi=120)
    plt.close(fig)
    return paths


def report(results, out_dir) -> None:
    """The benchmark's tables on stdout and its files in `out_dir` (`write_outputs`)."""
    if not results:
        print(f"no run finished; wrote {out_dir / 'runs-as-finished.csv'}")
        return
    print(format_table([r["row"] for r in results], [c for c in COLUMNS]))
    print()
    rows = summary(results)
    print(format_table(rows, list(rows[0])))
    print()
    rows = segment_table(results)
    print("runs through each segment:")
    print(format_table(rows, list(rows[0])))
    rows = breakdown(results)
    if rows:
        print("\nby the population's patients (sigmoid variant, sex, tercile of length):")
        print(format_table(rows, list(rows[0])))
    paths = write_outputs(results, out_dir)
    print(f"\nwrote {', '.join(str(p) for p in paths.values())}")
