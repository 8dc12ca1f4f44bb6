"""What the verbs share: the output folders they plan and claim, the Meshcat server, the
run's stop and exit status, and the contact and EPM lines a run prints."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import signal
import sys
from pathlib import Path

import yaml
from pydrake.geometry import Meshcat, MeshcatParams

from capsule_drake.app.cli_parser import DEFAULT_PORT, LOOPBACK
from capsule_drake.app.outputs import RUN_OUTPUTS, plan_outputs, release_claims
from capsule_drake.physics.tissue import INJURY_PRESSURE, ISCHAEMIA_PRESSURE
from capsule_drake.scenario import ScenarioError, load_scenario


# What a benchmark and an import write (a previous one's are replaced by --force).
BENCHMARK_OUTPUTS = ("runs.csv", "summary.csv", "progress.png", "segments.png", "results.json",
                     "runs-as-finished.csv")


IMPORT_OUTPUTS = ("wall.obj", "centerline.npz", "wall_radius.npz", "import.json")


# The commands that build colons, in the cache (anatomy/cache.py).
COLON_VERBS = ("run", "record", "teleop", "benchmark", "eval-lumen")


def planned_mcap(scenario, plan):
    """`scenario` writing its MCAP file where the plan checked it would go (the plan's
    resolved path of outputs.mcap.path), or unchanged when it writes none."""
    if plan.mcap is None or scenario.outputs.mcap is None:
        return scenario
    mcap = dataclasses.replace(scenario.outputs.mcap, path=str(plan.mcap))
    return dataclasses.replace(scenario, outputs=dataclasses.replace(scenario.outputs,
                                                                     mcap=mcap))


def _report_mcap(result) -> str | None:
    """Prints where the MCAP log is; or, when writing it failed, prints nothing and returns
    the failure (one line: `_finish` reports it)."""
    logger = result.channel_logger
    if logger is None:
        return None
    for line in logger.writer.dropped:   # a live output that stopped (said as it did)
        print(f"note: {line}", file=sys.stderr)
    log = logger.log
    if log is None:  # live outputs only, no MCAP file
        return None
    if log.error is not None:
        return f"--mcap {log.error}"
    print(f"MCAP log: {log.messages} ROS 2 messages in {log.path} (open it in Foxglove, "
          "or `ros2 bag info` it)")
    return None


def _finish(result, mcap_failure: str | None) -> int:
    """The run's stop, if it stopped early, and a failed MCAP log, on stderr (one line each;
    a run that stopped because the MCAP could not be written: one line); the exit status
    (`_exit_code`, and at least 1 when the MCAP log failed)."""
    stopped = result.metrics.get("stopped_early") or ""
    if mcap_failure is None or mcap_failure.removeprefix("--mcap ") not in stopped:
        _report_stop(result)
    code = _exit_code(result)
    if mcap_failure is not None:
        print(f"capsule-sim: error: {mcap_failure}", file=sys.stderr)
        code = code or 1
    return code


def _check_flag_combinations(args) -> None:
    """Refuses (ScenarioError: one line, exit 2) a flag that would do nothing in the
    combination given, before anything is loaded or written. What depends on the scenario
    (teleop's --port with the simulated operator) and on other flags' values (benchmark's
    --scenario, eval-lumen's light conditions) is checked where those are known."""
    if getattr(args, "force", False) and args.out is None and args.verb != "import-colon":
        has_mcap = hasattr(args, "mcap")
        if getattr(args, "mcap", None) is None:
            raise ScenarioError("--force: only with --out" + (" or --mcap" if has_mcap else "")
                                + " (it replaces a previous run's outputs there); without "
                                "--out, each run writes into a new folder")
    if args.verb == "run":
        if args.port is not None and not args.meshcat:
            raise ScenarioError("--port: only with --meshcat (the port of the live page; the "
                                "recording's own server takes any free port)")
    if args.verb == "benchmark":
        if args.address is not None and args.engine != "dask":
            raise ScenarioError("--address: only with --engine dask (the Dask scheduler the "
                                "benchmark runs on)")
        if args.workers is not None and args.address is not None:
            raise ScenarioError("--workers: not with --address (the scheduler's own workers "
                                "run the benchmark)")


def _plan(args, parent: str, name: str, outputs=RUN_OUTPUTS, *, mcap_bytes: float = 0.0,
          prefixes=(), inputs=(), scenario=None):
    """Every output path of the command, checked together before anything is built or run
    (app/outputs.py's `plan_outputs`): --out (refused if it holds files, unless --force) or
    a new folder parent/name-<date-time>, the MCAP file (`scenario`'s outputs.mcap.path,
    which --mcap spells; without a scenario, --mcap), and the `inputs` it reads."""
    if scenario is not None:
        mcap = scenario.outputs.mcap.path if scenario.outputs.mcap is not None else None
    else:
        mcap = getattr(args, "mcap", None)
    return plan_outputs(args.out, getattr(args, "force", None), parent=parent, name=name,
                        outputs=outputs, prefixes=prefixes, mcap=mcap,
                        mcap_bytes=mcap_bytes, inputs=inputs)


def _claim(plan) -> Path:
    """The planned folder, made (or a previous run's outputs removed from it, --force), and
    held by this command until it ends (another command naming it is refused)."""
    folder = plan.claim()
    if not plan.existed:
        _created_folders.append(folder)
    return folder


def _output_folder(args, parent: str, name: str, outputs=RUN_OUTPUTS) -> Path:
    """The folder a command writes into: --out (refused if it holds files, unless --force),
    or a new folder parent/name-<date-time> that no other run uses; checked (`_plan`), then
    made."""
    return _claim(_plan(args, parent, name, outputs))


# Output folders this command created: removed again if it fails before writing into them.
_created_folders: list[Path] = []


def _remove_unused_folders():
    release_claims()
    for folder in _created_folders:
        with contextlib.suppress(OSError):
            folder.rmdir()  # only if empty
    _created_folders.clear()


def _meshcat(host: str, port: int, announce: bool) -> Meshcat:
    """A Meshcat server on (host, port); its address printed when `announce` (a person will
    open it), Drake's own line silenced otherwise (a recording's server is noise)."""
    drake_log = logging.getLogger("drake")
    level = drake_log.level
    if not announce:
        drake_log.setLevel(logging.WARNING)
    try:
        meshcat = Meshcat(MeshcatParams(host=host, port=port))
    except RuntimeError as e:
        raise ScenarioError(f"--host {host} --port {port}: cannot start Meshcat "
                            f"({str(e).splitlines()[0]})") from None
    finally:
        drake_log.setLevel(level)
    if announce:
        print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
    return meshcat


def _exit_code(result) -> int:
    """0 for a run that ran its course (or reached its goal); 128 + the signal for an
    interrupted one; 1 for one the guard stopped or an error ended."""
    if result.status in ("completed", "goal"):
        return 0
    if result.status == "interrupted":
        return 128 + signal.Signals[result.metrics.get("signal", "SIGINT")].value
    return 1


def _report_stop(result) -> None:
    m = result.metrics
    if m.get("stopped_early"):
        print(f"stopped early: {m['stopped_early']}"
              + {"diverged": "; the simulation diverged, so no distance or force is "
                             "reported from it",
                 "perforated": "; the figures up to it are reported"}.get(result.status, ""),
              file=sys.stderr)


def _flags(**values) -> str:
    """YAML text of a command's flags, layered on the scenario before it is checked."""
    return yaml.safe_dump(values, default_flow_style=True, width=1 << 20).strip()


def _load(args, *flags: str):
    """The scenario of the command line: the file's named scenario, the user's
    --scenario-text over it, then the command's own flags (YAML texts, the output flags
    among them: `output_flags`), then checked once."""
    overrides = [args.scenario_text]
    if args.duration is not None:
        overrides.append(_flags(duration=args.duration))
    return load_scenario(args.scenario_file, args.scenario,
                         overrides + output_flags(args) + list(flags))


def output_flags(args) -> list[str]:
    """The output flags a command has, as what they spell in the scenario's `outputs`:
    --mcap FILE (outputs.mcap.path), --meshcat with --host/--port (outputs.meshcat),
    --no-recording (outputs.recording false), --foxglove [PORT] (outputs.foxglove),
    --ros2 [DOMAIN] (outputs.ros2)."""
    outputs = {}
    host = getattr(args, "host", None)
    if getattr(args, "mcap", None) is not None:
        outputs["mcap"] = {"path": str(args.mcap)}
    if getattr(args, "meshcat", False):
        outputs["meshcat"] = {"host": host or LOOPBACK,
                              "port": DEFAULT_PORT if args.port is None else args.port}
    if getattr(args, "no_recording", False):
        outputs["recording"] = False
    if getattr(args, "foxglove", None) is not None:
        outputs["foxglove"] = {"host": host or LOOPBACK, "port": args.foxglove}
    if getattr(args, "ros2", None) is not None:
        outputs["ros2"] = {"domain_id": args.ros2, "loopback": host in (None, LOOPBACK)}
    return [_flags(outputs=outputs)] if outputs else []


def contact_words(m: dict) -> str:
    """How a printed contact figure names the model it comes from (metrics' contact_model,
    physics/contact/), and, for the rigid stand-in, that its figures are the stand-in's."""
    model = m.get("contact_model")
    if model is None:   # metrics of a run before the models were named
        return "contact"
    if model.startswith("rigid"):
        return f"contact on the {model}, not a tissue figure"
    return f"contact on the {model}"


def pressure_summary(m: dict) -> str | None:
    """The run's pressure on the colon wall as one line, from its metrics' per-patch figures
    (io/metrics.py `site_pressure_metrics`): the highest pressure any patch of the wall felt
    and where, and the longest time ONE patch spent above each threshold (physics/tissue.py:
    330 kPa, mucosal injury; 4.0 kPa, blood flow falls) and where. "none" when the contact
    has no pressure field; None (nothing to say) for a run without the map or whose figures
    are null (it diverged, or ended before a sample)."""
    if "wall_pressure_field" not in m:
        return None
    patch = f"{m['wall_patch_length_m'] * 100:.0f} cm x {m['wall_patch_angle_deg']:.0f} deg"
    patch = f"{patch} patch" + (f", {contact_words(m)}" if "contact_model" in m else "")
    if not m["wall_pressure_field"]:
        return f"wall pressure per {patch}: none (the contact has no pressure field)"
    if m.get("site_peak_pressure_kPa") is None:
        return None

    def where(prefix):
        s = m.get(f"{prefix}_at_s_m")
        return f" ({m[f'{prefix}_segment']}, {s * 100:.1f} cm)" if s is not None else ""

    return (f"wall pressure per {patch}: peak {m['site_peak_pressure_kPa']:.0f} kPa"
            f"{where('site_peak')}; longest on one patch above {INJURY_PRESSURE / 1000:.0f} "
            f"kPa (mucosal injury) {m['site_longest_above_injury_s']:.2f} s, above "
            f"{ISCHAEMIA_PRESSURE / 1000:.1f} kPa (blood flow falls) "
            f"{m['site_longest_above_ischaemia_s']:.2f} s"
            f"{where('site_longest_above_ischaemia')}")


def _report_pressure(m: dict) -> None:
    """Prints `pressure_summary`'s line, if it has one."""
    line = pressure_summary(m)
    if line is not None:
        print(line)


def _report_epm_guard(metrics) -> None:
    """One line when the EPM guard (epm/guard.py) had to change the driver's commands."""
    changed = {name: metrics.get(f"epm_commands_{name}", 0)
               for name in ("raised", "clamped", "rejected")}
    if any(changed.values()):
        print(f"EPM guard: of {metrics.get('epm_commands', 0)} pose commands, "
              f"{changed['raised']} raised to the clearance, {changed['clamped']} clamped "
              f"to the workspace, {changed['rejected']} rejected (not finite: the last safe "
              f"one held)")
