"""A run's logs spooled to disk as it goes (logs.parts/, joined into logs.npz at the end) and
read back: nothing logged is lost if the run is interrupted."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from capsule_drake.app.outputs import save_npz


LOG_KEYS = ("times", "capsule_state", "contact_load", "contact_pressure", "epm_pose")
"""What logs.npz holds (samples along the last axis): times (s), capsule_state (13: quaternion
wxyz, p_WC, w, v), contact_load (N), contact_pressure (the contact's peak pressure, Pa: NaN
for point contact), epm_pose (6: centre, moment direction)."""


class LogSpool:
    """Appends a run's logged samples to `folder`/logs.parts/ as the run goes.

    `add(chunk)` keeps a chunk of samples (a dict of LOG_KEYS arrays, samples along the last
    axis) in memory and writes the chunks not yet on disk when `period` simulated seconds
    or `wall_period` seconds of wall time have passed since the last write. `finish()`
    writes logs.npz (all samples) and removes logs.parts/. Without a folder it only keeps
    the chunks (a run with no outputs).
    """

    def __init__(self, folder: Path | None, period: float = 5.0, wall_period: float = 10.0):
        self.folder = Path(folder) if folder is not None else None
        self.period, self.wall_period = period, wall_period
        self.chunks: list[dict] = []
        self._written = 0
        self._last_t = 0.0
        self._last_wall = time.monotonic()

    @property
    def parts_dir(self) -> Path:
        return self.folder / "logs.parts"

    def add(self, chunk: dict, t: float) -> None:
        if chunk["times"].size:
            self.chunks.append(chunk)
        if self.folder is not None and (t - self._last_t >= self.period or
                                        time.monotonic() - self._last_wall >= self.wall_period):
            self.flush(t)

    def flush(self, t: float | None = None) -> None:
        """Writes the chunks not yet on disk as one part file."""
        if t is not None:
            self._last_t = t
        self._last_wall = time.monotonic()
        pending = self.chunks[self._written:]
        if self.folder is None or not pending:
            return
        self.parts_dir.mkdir(exist_ok=True)
        save_npz(self.parts_dir / f"part-{self._written:06d}.npz", _joined(pending))
        self._written = len(self.chunks)

    def joined(self) -> dict:
        return _joined(self.chunks)

    def finish(self) -> None:
        """logs.npz with every sample; the parts are removed once it is written."""
        if self.folder is None:
            return
        save_npz(self.folder / "logs.npz", self.joined())
        if self.parts_dir.is_dir():
            shutil.rmtree(self.parts_dir, ignore_errors=True)


def _joined(chunks: list[dict]) -> dict:
    if not chunks:
        return {"times": np.zeros(0), "capsule_state": np.zeros((13, 0)),
                "contact_load": np.zeros(0), "contact_pressure": np.zeros(0),
                "epm_pose": np.zeros((6, 0))}
    return {key: np.concatenate([c[key] for c in chunks], axis=-1) for key in LOG_KEYS}


def load_logs(folder: Path | str) -> dict[str, np.ndarray]:
    """A run's logs: logs.npz, or for a run killed before it could write that, the parts
    in logs.parts/ joined in order."""
    folder = Path(folder)
    if (folder / "logs.npz").is_file():
        with np.load(folder / "logs.npz") as data:
            return {key: data[key] for key in data.files}
    parts = sorted((folder / "logs.parts").glob("part-*.npz"))
    if not parts:
        raise FileNotFoundError(f"{folder}: no logs.npz and no logs.parts/")
    chunks = []
    for part in parts:
        with np.load(part) as data:
            # Parts of a run from before a key was logged lack it: NaN samples in its place.
            chunks.append({key: data[key] if key in data.files else
                           np.full(len(data["times"]), np.nan) for key in LOG_KEYS})
    return _joined(chunks)
