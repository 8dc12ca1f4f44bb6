"""eval-lumen's work (`capsule-sim eval-lumen`): frames rendered on each image path, every
detector scored on every condition, the tables, results.json and contact sheets written
as they are made (perception/evaluation.py scores one detector on one set of frames)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2

from capsule_drake.app.outputs import write_atomic
from capsule_drake.app.run_outputs import WriteError
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.perception.evaluation import (IMAGE_CONDITIONS, DetectorError,
                                                 condition_frames, condition_table, evaluate,
                                                 finite_or_none, meets, mixed_sheet)
from capsule_drake.perception.lens import LensConfig

OUTPUTS = ("results.json", "tables.md", "error.txt")
"""What eval-lumen writes besides its contact sheets (error.txt: a detector's traceback)."""


class EvaluationStopped(Exception):
    """A detector failed: the message names it and where what was scored before is."""


def evaluate_paths(detectors: dict, renderers, lenses, conditions, out_dir: Path, *,
                   frames: int, colons: int, seed: int, wall_fraction: float,
                   quiet: bool = False) -> list[str]:
    """Every detector on every image path (renderer x lens) and condition (the raycast
    renderer's light conditions only on it); writes results.json and tables.md into
    `out_dir`. Returns the (detector, path, condition) that miss the targets. Raises
    EvaluationStopped when a detector fails, after writing what was scored (and its
    traceback, error.txt)."""
    results, tables = {}, []
    try:
        for renderer in renderers:
            on_path = [c for c in conditions if c in IMAGE_CONDITIONS or renderer == "raycast"]
            if on_path:
                for lens in lenses:
                    _evaluate_path(detectors, renderer, lens, on_path, out_dir, results,
                                   tables, frames=frames, colons=colons, seed=seed,
                                   wall_fraction=wall_fraction, quiet=quiet)
    except DetectorError as e:
        # What was scored before the failure is kept; the user's traceback beside it.
        where = f"what was scored before it is in {out_dir}/ (results.json, tables.md)"
        if e.details is not None:
            write_file(out_dir / "error.txt", e.details)
            where = f"the traceback is in {out_dir}/error.txt; " + where
        tables.append(f"Stopped: {e}")
        write_results(out_dir, results, tables)
        raise EvaluationStopped(f"{e}; {where}") from None
    write_results(out_dir, results, tables)
    return [f"{name} {path} {condition}" for name, paths in results.items()
            for path, summaries in paths.items() for condition, summary in summaries.items()
            if not meets(summary, path.split("_")[-1])]


def _evaluate_path(detectors, renderer, lens, conditions, out_dir, results, tables, *,
                   frames: int, colons: int, seed: int, wall_fraction: float, quiet: bool):
    """One image path (renderer, lens): renders the frames, scores each detector on them
    (its summaries into `results`, its table into `tables`, as they are made: a detector
    that fails leaves what came before) and saves its contact sheet."""
    path = f"{renderer}, {lens}"

    def progress(done):
        if quiet:
            return
        if sys.stderr.isatty():
            print(f"\r{path}: rendered {done} / {frames} poses",
                  end="\n" if done == frames else "", file=sys.stderr, flush=True)
        elif done % max(1, frames // 5) == 0 or done == frames:
            print(f"{path}: rendered {done} / {frames} poses", file=sys.stderr)

    config = CameraConfig(lens=LensConfig(
        model="pinhole_radtan" if lens == "pinhole" else "equidistant"))
    rendered = condition_frames(frames, colons, seed, renderer, conditions, config,
                                wall_fraction, progress=progress)
    for name, detector in detectors.items():
        summaries = results.setdefault(name, {}).setdefault(f"{renderer}_{lens}", {})
        for condition, of_condition in rendered.items():
            summaries[condition] = evaluate(of_condition, detector, name,
                                            f"{path}, {condition}").summary()
        table = condition_table(summaries, f"{name} on {path} frames (colon seeds "
                                           f"{seed}-{seed + colons - 1}, {frames} poses)",
                                lens)
        tables.append(table)
        print(table + "\n", flush=True)
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
        sheet = cv2.cvtColor(mixed_sheet(rendered, detector, name=name, where=path),
                             cv2.COLOR_RGB2BGR)
        sheet_path = out_dir / f"{safe}_{renderer}_{lens}_sheet.png"
        if not cv2.imwrite(str(sheet_path), sheet):
            raise WriteError(f"{sheet_path}: could not write the contact sheet")


def write_file(path: Path, text: str) -> None:
    try:
        write_atomic(path, text)
    except OSError as e:
        raise WriteError(f"{path.parent}: could not write {path.name} "
                         f"({e.strerror or e})") from None


def write_results(out_dir: Path, results: dict, tables: list[str]) -> None:
    """results.json (only the scores made: a detector path or condition not reached is
    absent) and tables.md."""
    kept = {name: {path: summaries for path, summaries in paths.items() if summaries}
            for name, paths in results.items()}
    write_file(out_dir / "results.json",
                     json.dumps(finite_or_none({k: v for k, v in kept.items() if v}), indent=2))
    write_file(out_dir / "tables.md", "\n\n".join(tables) + "\n")
