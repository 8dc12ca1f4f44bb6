"""One run of the benchmark: its task (a navigator on a seeded colon), its scenario, and
what it measures (the row's columns, the progress curve, the segments passed)."""

from __future__ import annotations

import dataclasses
import os
import time

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
from capsule_drake.physics.contact.tissue import TISSUE_COLUMN_DOCS, TISSUE_COLUMNS
from capsule_drake.plugins import load_function
from capsule_drake.scenario import load_scenario
from capsule_drake.station import station_value

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
# What each column is, ending in its unit in parentheses ("(1)": a plain number or fraction;
# "(text)", "(count)", "(true/false)"); the documentation's reference is generated from it
# (app/reference.py). A column without one fails at import.
COLUMN_DOCS = {
    "navigator": "the navigator: a built-in one (NAVIGATORS) or a user's "
                 "\"package.module:function\" (text)",
    "seed": "the colon's seed, colon.seed (count)",
    "colon_cm": "length of the colon's centreline, anus to cecal pole (cm)",
    "patient": "the population patient's sex and sigmoid variant (\"female, redundant "
               "sigmoid\"), \"\" for a colon not drawn from the population (text)",
    **TISSUE_COLUMN_DOCS,
    "reached_cecum": "whether the capsule's centreline station came within CECUM_MARGIN "
                     "(4 cm) of the centreline's end (true/false)",
    "time_to_cecum_s": "simulated time of the first logged sample within CECUM_MARGIN of "
                       "the end; NaN if the capsule never got there (s)",
    "progress": "furthest centreline station reached, as a share of the way from the start "
                "station to the end: (furthest - start) / (length - start) (1)",
    "progress_cm": "furthest centreline station reached minus the start station (cm)",
    "stuck_in": "why a run that did not reach the cecum ended: the reason it was stopped "
                "early (guard, clearance, error), else the segment it stalled in (no "
                "STALL_ADVANCE = 1 cm of progress in the last STALL_WINDOW = 30 s), or "
                "\"time limit (segment, at N cm)\" if it was still advancing; \"\" when it "
                "reached the cecum (text)",
    "wall_contact_s": "simulated time during which the summed contact force on the capsule "
                      "exceeded CONTACT_THRESHOLD (0.05 N), over the logged samples (s)",
    "peak_contact_force_N": "largest summed magnitude of the contact forces (hydroelastic "
                            "surfaces, point contacts and the compliant wall's), over the "
                            "logged samples (N)",
    "peak_contact_pressure_kPa": "highest contact pressure over the logged samples; NaN "
                                 "for point contact, which has no pressure field (kPa)",
    "injury_pressure_s": "simulated time the contact's peak pressure spent above the "
                         "injury threshold, 330 kPa (physics/tissue.py); NaN for point "
                         "contact (s)",
    "site_peak_pressure_kPa": "highest pressure any one patch of the wall felt "
                              "(physics/wall_pressure.py); NaN without a pressure field (kPa)",
    "site_injury_s": "longest time one patch of the wall spent above 330 kPa without a "
                     "break; NaN without a pressure field (s)",
    "site_ischaemia_s": "longest time one patch of the wall spent above the ischaemia "
                        "threshold, 4.0 kPa (30 mmHg), without a break; NaN without a "
                        "pressure field (s)",
    "centring_error_deg": "median, over the logged samples where the lumen truth is in "
                          "view, of the angle between the camera's optical axis and the ray "
                          "to the lumen truth's pixel (capsule.lumen.lumen_pixel); NaN "
                          "without a camera (deg)",
    "detection_error_pct": "median distance between the lumen tracker's pixel and the "
                           "image-side truth's (capsule.lumen.far_pixel) where both see the "
                           "lumen, in % of the image diagonal; NaN without a tracker (%)",
    "detection_rate": "share of the samples with the lumen in view (image-side truth) that "
                      "the tracker reported visible; NaN without a tracker (1)",
    "detection_fp_rate": "share of the samples without the lumen in view that the tracker "
                         "reported visible (false positives); NaN without a tracker (1)",
    "loc_pos_err_median_mm": "median, over the logged samples, of the distance between the "
                             "localiser's estimated and the true capsule position; NaN "
                             "without capsule.localizer (mm)",
    "loc_pos_err_p95_mm": "95th percentile of that position error; NaN without "
                          "capsule.localizer (mm)",
    "loc_rot_err_median_deg": "median angle of the rotation between the localiser's "
                              "estimated and the true capsule orientation; NaN without "
                              "capsule.localizer (deg)",
    "epm_path_m": "length of the path of the EPM's centre, summed between logged samples (m)",
    "coverage": "share of the area of the camera's wall mesh that a frame showed by the end "
                "of the run (navigation/coverage.py); NaN without a camera (1)",
    "polyps_diminutive": "polyps of at most 5 mm in the colon (count)",
    "seen_diminutive": "of those, the ones the camera showed for at least SEEN_SECONDS "
                       "(0.2 s; navigation/lesions_seen.py); NaN without a camera (count)",
    "polyps_small": "polyps of 6-9 mm in the colon (count)",
    "seen_small": "of those, the ones shown for at least 0.2 s; NaN without a camera (count)",
    "polyps_large": "polyps of 10 mm or more in the colon (count)",
    "seen_large": "of those, the ones shown for at least 0.2 s; NaN without a camera (count)",
    "polyps_detected": "polyps seen (shown for at least 0.2 s) that the user's polyp "
                       "detector (Task.polyp_detector) marked in at least one frame; NaN "
                       "without a detector (count)",
    "polyp_fp_per_min": "the polyp detector's false positives (marks on no polyp) per "
                        "minute of frames; NaN without a detector (1/min)",
    "diverticula": "diverticula in the colon (count)",
    "seen_diverticula": "of those, the ones shown for at least 0.2 s; NaN without a camera "
                        "(count)",
    "sim_time_s": "simulated time at which the run ended (s)",
    "wall_time_s": "wall-clock time of the run's simulation, from its first step to its "
                   "end (the build excluded; a failed run's: its whole time) (s)",
    "status": "\"finished\" (the row measures the run, whatever ended it) or \"failed\" "
              "(text)",
    "error": "how a failed run failed (a crash, its wall-time limit, an exception, naming "
             "the plug-in that raised if one did); \"\" for a finished run (text)",
}
if set(COLUMN_DOCS) != set(COLUMNS):
    raise RuntimeError("benchmark columns without a COLUMN_DOCS entry, or entries without "
                       f"a column: {sorted(set(COLUMNS) ^ set(COLUMN_DOCS))}")
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
            lens, tick, latency = (station_value(station, f"capsule.camera.{name}")
                                   for name in ("lens", "tick", "latency"))
            coverage = builder.AddNamedSystem("coverage", MucosaCoverage(
                colon, lens, scenario.capsule.camera.far))
            for name in ("depth_image", "frame_info", "frame_pose"):
                builder.Connect(station.GetOutputPort(f"capsule.camera.{name}"),
                                coverage.GetInputPort(name))
            extra["coverage"] = LogVectorOutput(coverage.GetOutputPort("coverage"), builder, 1.0)
            for name in ("lumen_pixel", "lumen_visible", "far_pixel", "far_visible"):
                extra[name] = LogVectorOutput(station.GetOutputPort(f"capsule.lumen.{name}"),
                                              builder, period)
            extra["lens"] = lens
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
                    int(lens.pixel_rays()[1].sum()), tick, latency + 1e-6, detector=scorer))
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
    lens = extra.pop("lens", None)
    data = {name: log.FindLog(result.context) for name, log in extra.items()}
    stopped = result.metrics.get("stopped_early")
    row = _metrics(task, colon, result, data, lens, stopped)
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


def _metrics(task, colon, result, data, lens, stopped) -> dict:
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
    if lens is not None and "lumen_pixel" in data:
        pixel, visible = _logged_lumen(data, "lumen")
        if visible.any():
            rays = lens.unproject(pixel[visible])
            angles = np.degrees(np.arccos(np.clip(rays[:, 2] / np.linalg.norm(rays, axis=1),
                                                  -1.0, 1.0)))
            centring = float(np.median(angles))
    detection_error, detection_rate, false_positives = _detection_scores(lens, data)
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


def _detection_scores(lens, data) -> tuple[float, float, float]:
    """How the run's lumen tracker did against the image-side truth (perception/
    lumen_truth.py, `far_region` of each frame's range image), sampled together: the median
    distance between detected and true pixel (% of the image diagonal) where both see the
    lumen, the share of lumen-in-view samples the tracker reported visible, and the share of
    samples without a lumen in view that it reported visible (false positives). NaN for a run
    without a tracker (or a measure with no samples). Tracker and truth both hold the last
    frame's result; they may be a frame apart for the tracker's reading delay."""
    if lens is None or "tracker_lumen_pixel" not in data or "far_pixel" not in data:
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
    diagonal = float(np.hypot(lens.width, lens.height))
    error = 100.0 * float(np.median(np.linalg.norm(found[both] - truth[both], axis=1))) / diagonal
    return error, rate, false_positives

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

