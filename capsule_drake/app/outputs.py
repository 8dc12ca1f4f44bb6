"""A run's output folder: chosen without overwriting, checked before the run, written as
the run goes, and complete on every way a run can end.

- `new_run_folder` makes a folder no other run has (runs/Default-20261124-101530, then
  ...-2, ...-3 for runs started in the same second); `claim_folder` takes a folder the user
  named, refusing one that holds files unless told to replace a previous run's outputs.
- `check_room` writes a probe file and compares the free space with what the run will
  write, so a read-only or full disk is a one-line error before the simulation, not a
  traceback after it.
- `LogSpool` appends the logged samples to logs.parts/ every few simulated seconds (and at
  least every few seconds of wall time), so a process that is killed outright (kill -9, a
  power cut) loses at most that much; at the end they become logs.npz. `load_logs` reads
  either.
- `write_atomic` writes through a temporary file and a rename: a full disk leaves the
  previous file or none, never a truncated one.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from pathlib import Path

import numpy as np

# What a run writes into its folder (a previous run's are removed by --force).
RUN_OUTPUTS = ("metrics.json", "scenario.yaml", "logs.npz", "recording.html", "logs.parts")
# Bytes of one logged sample: time, capsule state (13), contact load, EPM pose (6), as float64.
SAMPLE_BYTES = 8 * (1 + 13 + 1 + 6)
# A Meshcat recording: the scene's meshes (~16 MB for the procedural colon), then the
# animation (measured: 16.2 MB for 3.4 s of the Default run, 16-18 MB for 60 s).
RECORDING_BYTES = 20e6
RECORDING_BYTES_PER_S = 0.05e6
# Room kept free beyond the estimate (bytes).
SPARE_BYTES = 20e6


class OutputError(ValueError):
    """The output folder cannot be used; the message is one line naming it."""


def _reason(e: OSError) -> str:
    return e.strerror or str(e)


def new_run_folder(parent: Path | str, name: str) -> Path:
    """A new, empty folder parent/<name>-<date-time>[-k] that no other run uses."""
    parent = Path(parent)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{parent}: cannot create the output folder ({_reason(e)})") from None
    for k in range(1, 10000):
        folder = parent / (f"{name}-{stamp}" if k == 1 else f"{name}-{stamp}-{k}")
        try:
            folder.mkdir()
            return folder
        except FileExistsError:
            continue
        except OSError as e:
            raise OutputError(f"{folder}: cannot create the output folder "
                              f"({_reason(e)})") from None
    raise OutputError(f"{parent}: too many runs named {name}-{stamp}")


def claim_folder(folder: Path | str, force: bool | None = False, what: str = "--out",
                 outputs: tuple[str, ...] = RUN_OUTPUTS) -> Path:
    """The folder a user named for a run's outputs, created if need be.

    An existing folder that holds anything is refused (a previous run's outputs would be
    overwritten, or mixed with the new ones); with `force`, a previous run's outputs
    (`outputs`) are removed first, and other files are left alone. `force` None: the
    command has no --force (a dataset is never replaced).
    """
    if str(folder) == "":
        raise OutputError(f"{what}: empty path (give a folder, e.g. {what} runs/mine)")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{what} {folder}: exists and is not a folder")
    if folder.is_dir():
        try:
            entries = sorted(p.name for p in folder.iterdir())
        except OSError as e:
            raise OutputError(f"{what} {folder}: cannot read the folder ({_reason(e)})") from None
        if entries and not force:
            shown = ", ".join(entries[:4]) + (", ..." if len(entries) > 4 else "")
            raise OutputError(f"{what} {folder}: folder exists and holds {shown}; choose "
                              "another folder" + ("" if force is None else
                                                  ", or add --force to replace a previous "
                                                  "run's outputs there"))
        for name in outputs if force else ():
            path = folder / name
            try:
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                elif path.exists() or path.is_symlink():
                    path.unlink()
            except OSError as e:
                raise OutputError(f"{what} {folder}: cannot remove the previous {name} "
                                  f"({_reason(e)})") from None
        return folder
    try:
        folder.mkdir(parents=True)
    except OSError as e:
        raise OutputError(f"{what} {folder}: cannot create the output folder "
                          f"({_reason(e)})") from None
    return folder


def run_output_bytes(duration: float, log_period: float, recording: bool) -> float:
    """Bytes a run of `duration` will write (logs uncompressed, plus the recording)."""
    return (duration / log_period + 1) * SAMPLE_BYTES + (
        RECORDING_BYTES + RECORDING_BYTES_PER_S * duration if recording else 0.0)


def check_room(folder: Path, needed_bytes: float, free_bytes=None) -> None:
    """Raises OutputError unless `folder` can be written and has room for `needed_bytes`
    (and SPARE_BYTES more). `free_bytes` overrides the measured free space (tests)."""
    probe = folder / ".write-check"
    try:
        probe.write_bytes(b"capsule-sim")
        probe.unlink()
    except OSError as e:
        raise OutputError(f"{folder}: cannot write to the output folder ({_reason(e)})") from None
    free = shutil.disk_usage(folder).free if free_bytes is None else free_bytes
    if free < needed_bytes + SPARE_BYTES:
        raise OutputError(f"{folder}: {free / 1e6:.0f} MB free, but the run will write about "
                          f"{needed_bytes / 1e6:.0f} MB (and {SPARE_BYTES / 1e6:.0f} MB are "
                          "kept spare); free some space or choose another --out")


def write_atomic(path: Path, data: str | bytes | None = None, writer=None) -> None:
    """Writes `data` (or calls `writer(temporary_path)`) to a temporary file beside `path`
    and renames it over `path`: a failure leaves no partial file. Raises OSError."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.partial")
    try:
        if writer is not None:
            writer(temporary)
        elif isinstance(data, bytes):
            temporary.write_bytes(data)
        else:
            temporary.write_text(data)
        with open(temporary, "rb") as f:
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException:
        try:
            temporary.unlink()
        except OSError:
            pass
        raise


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez_compressed, atomically (write_atomic)."""
    def writer(temporary):
        with open(temporary, "wb") as f:
            np.savez_compressed(f, **arrays)
    write_atomic(path, writer=writer)


LOG_KEYS = ("times", "capsule_state", "contact_load", "epm_pose")


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
                "contact_load": np.zeros(0), "epm_pose": np.zeros((6, 0))}
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
            chunks.append({key: data[key] for key in LOG_KEYS})
    return _joined(chunks)


def is_disk_full(e: OSError) -> bool:
    return e.errno in (errno.ENOSPC, errno.EDQUOT)
