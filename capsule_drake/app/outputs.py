"""A run's output folder: chosen without overwriting, checked before the run, written as
the run goes, and complete on every way a run can end.

- `new_run_folder` makes a folder no other run has (runs/Default-20261124-101530, then
  ...-2, ...-3 for runs started in the same second); `claim_folder` takes a folder the user
  named, refusing one that holds files unless told to replace a previous run's outputs.
- A command holds the folder it writes into (`OutputPlan.claim`) until it ends: an
  exclusive lock on the folder itself (flock), which the system releases when the process
  ends, however it ends (kill -9 too), so a claim never outlives its command. A second
  command that names the same folder, with --force or not, at the same moment or while the
  first runs, is refused in one line. `release_claims` lets go of them before the end.
- `check_room` writes a probe file and compares the free space with what the run will
  write, so a read-only or full disk is a one-line error before the simulation, not a
  traceback after it; the probe is removed even when writing it fails.
- `LogSpool` (app/log_spool.py) appends the logged samples to logs.parts/ every few
  simulated seconds (and at least every few seconds of wall time), so a process that is
  killed outright (kill -9, a power cut) loses at most that much; at the end they become
  logs.npz. `load_logs` (there too) reads either.
- `write_atomic` writes through a temporary file and a rename: a full disk leaves the
  previous file or none, never a truncated one.
- `plan_outputs` is the one place where a command's output paths are checked together,
  before anything is built or run: the folder (--out, or a new one), the file --mcap
  names, and the input files the command reads. It refuses a path that is not a regular
  file or a folder (a device, a named pipe, a socket), a symbolic link where a file is to
  be written, a file that is not a previous output of this simulator (even with --force),
  a folder that cannot be created or written, a folder another command is writing into,
  and any two outputs (or an output and an input) that are the same file. Only then does
  `OutputPlan.claim` create the folder (or take it), check it again under its lock, and
  remove what an interrupted write left (the probe, write_atomic's temporary files) and,
  with --force, a previous run's outputs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import os
import shutil
import stat
import struct
import time
from pathlib import Path

import numpy as np

# What a run writes into its folder (a previous run's are removed by --force); error.txt
# only after an error inside the simulation.
RUN_OUTPUTS = ("metrics.json", "scenario.yaml", "logs.npz", "recording.html", "logs.parts",
               "error.txt", "wall_pressure.npz", "wall_pressure.png")
# Of those, the folders (the others are files).
OUTPUT_FOLDERS = ("logs.parts", "Frames")
# What `capsule-sim record` writes into a dataset folder (app/dataset.py), besides a run's.
DATASET_OUTPUTS = ("README.md", "camera.yaml", "sensors.yaml", "mask.png", "Frames",
                   "SavedPosition.txt", "SavedRotationQuaternion.txt", "frames.csv",
                   "lumen_truth.csv", "imu.csv", "ahrs.csv", "magnetometer.csv",
                   "ground_truth.csv") + RUN_OUTPUTS
# What `record --seeds` writes into its folder: these and one dataset folder per seed,
# named SEED_PREFIX + the seed.
SEEDS_OUTPUTS = ("splits.csv", "README.md")
SEED_PREFIX = "seed_"
# The start of an MCAP file (the magic, then the header record: opcode 1, its length, the
# profile and library strings) and the library this simulator's MCAP files name there.
MCAP_MAGIC = b"\x89MCAP0\r\n"
MCAP_LIBRARY = "capsule_drake"
# Bytes of one logged sample: time, capsule state (13), contact load, EPM pose (6), as float64.
SAMPLE_BYTES = 8 * (1 + 13 + 1 + 6)
# A Meshcat recording: the scene's meshes (~16 MB for the procedural colon), then the
# animation (measured: 16.2 MB for 3.4 s of the Default run, 16-18 MB for 60 s).
RECORDING_BYTES = 20e6
RECORDING_BYTES_PER_S = 0.05e6
# The map of the wall's pressure and its picture (wall_pressure.npz, .png: measured 3-4 kB
# and 70-90 kB), with room to spare.
WALL_MAP_BYTES = 0.3e6
# Room kept free beyond the estimate (bytes).
SPARE_BYTES = 20e6
# The probe `check_room` writes; `write_atomic` writes `path` through ".<name>" + PARTIAL.
PROBE_NAME = ".write-check"
PARTIAL = ".partial"


class OutputError(ValueError):
    """The output folder cannot be used; the message is one line naming it."""


def _reason(e: OSError) -> str:
    return e.strerror or str(e)


def _leftovers(outputs: tuple[str, ...]) -> set[str]:
    """What an interrupted write of a command with these `outputs` can leave in its
    folder: the probe, and the temporary file of each output (`write_atomic`)."""
    return {PROBE_NAME} | {f".{name}{PARTIAL}" for name in outputs}


# The folders this process holds (folder -> the descriptor holding its lock).
_claims: dict[Path, int] = {}


def _in_use_error(what: str, folder: Path) -> OutputError:
    return OutputError(f"{what} {folder}: another capsule-sim command is writing into this "
                       f"folder; wait until it ends, or choose another {what}")


def _lock(folder: Path, what: str) -> None:
    """Holds `folder` for this process (an exclusive flock on the folder, released by the
    system when the process ends); OutputError if another command holds it. A file system
    without locks (some network ones) is used without."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError as e:
        raise OutputError(f"{what} {folder}: cannot open the output folder "
                          f"({_reason(e)})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise _in_use_error(what, folder) from None
    except OSError:
        pass  # no locks here: the folder is used as it was before claims existed
    _claims[folder] = fd


def _held_elsewhere(folder: Path) -> bool:
    """Whether a command (another process, or an earlier claim of this one) holds `folder`;
    nothing is held after the look."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # and with it the lock, if it was taken
    return False


def release(folder: Path) -> None:
    """Lets go of this process's claim on `folder` (if it holds one)."""
    fd = _claims.pop(Path(folder), None)
    if fd is not None:
        os.close(fd)


def release_claims() -> None:
    """Lets go of every folder this process holds (the command has ended); the system
    does it anyway when the process ends."""
    for folder in list(_claims):
        release(folder)


def new_run_folder(parent: Path | str, name: str) -> Path:
    """A new, empty folder parent/<name>-<date-time>[-k] that no other run uses (made with
    mkdir, which fails for a folder that exists: two runs never get the same one)."""
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
    command has no --force (a dataset is never replaced). `plan_outputs`, then `claim`.
    """
    return plan_outputs(folder, force, outputs=outputs, what=what).claim()


@dataclasses.dataclass
class OutputPlan:
    """Every path a command will write, checked together by `plan_outputs`.

    folder: the folder the user named (--out), or None: a new folder parent/name-<date-time>.
    mcap: the MCAP file (--mcap), or None. existed: whether `folder` existed before.
    """

    folder: Path | None
    parent: Path
    name: str
    force: bool | None
    outputs: tuple[str, ...]
    what: str = "--out"
    mcap: Path | None = None
    existed: bool = False

    def claim(self) -> Path:
        """Creates the folder (or a new one) and holds it until the command ends (`_lock`:
        a folder another command holds is refused); then, checked again under the lock
        (another command may have written into it since the plan), removes what an
        interrupted write left there and, with --force, a previous run's outputs; returns
        it. Raises OutputError."""
        if self.folder is None:
            folder = new_run_folder(self.parent, self.name)
            _lock(folder, self.what)
            return folder
        folder = self.folder
        if not self.existed:
            try:
                folder.mkdir(parents=True)
            except FileExistsError:  # made since the plan, by another command: the lock
                self.existed = True  # and the checks under it decide
            except OSError as e:
                raise OutputError(f"{self.what} {folder}: cannot create the output folder "
                                  f"({_reason(e)})") from None
        _lock(folder, self.what)
        try:
            _check_folder(folder, self.force, self.what, self.outputs, held=True)
            removed = sorted(_leftovers(self.outputs)) + list(
                self.outputs if self.force else ())
            for name in removed:
                path = folder / name
                try:
                    if name in OUTPUT_FOLDERS and path.is_dir() and not path.is_symlink():
                        shutil.rmtree(path)
                    elif os.path.lexists(path):
                        path.unlink()
                except OSError as e:
                    raise OutputError(f"{self.what} {folder}: cannot remove the previous "
                                      f"{name} ({_reason(e)})") from None
        except BaseException:
            release(folder)
            raise
        return folder


def plan_outputs(out: Path | str | None, force: bool | None = False, *,
                 parent: Path | str = "runs", name: str = "run",
                 outputs: tuple[str, ...] = RUN_OUTPUTS, prefixes: tuple[str, ...] = (),
                 mcap: Path | str | None = None, mcap_bytes: float = 0.0,
                 inputs=(), what: str = "--out") -> OutputPlan:
    """Checks every output path of a command before anything is made, built or run, and
    returns the plan (`OutputPlan.claim` then makes the folder). Raises OutputError (one
    line naming the path) on the first problem:

    - the folder `out` (`what`, e.g. --out; None: a new folder parent/name-<date-time>) is
      not a folder, is held by another command (`OutputPlan.claim`), holds files (unless
      `force`, and then only a previous run's `outputs` are removed, each of the kind this
      simulator writes: a regular file, or one of OUTPUT_FOLDERS; what an interrupted
      write leaves, `_leftovers`, does not count), or cannot be created or written;
    - the `mcap` file (`check_file_output`) is not a regular file, is a symbolic link, is an
      existing file that is not an MCAP log of this simulator (even with `force`), or its
      folder is missing or cannot be written, or has no room for `mcap_bytes`;
    - two outputs are the same path: the MCAP is the folder, or one of `outputs` (or a name
      starting with one of `prefixes`, e.g. a dataset's seed_ folders) in it, or the folder
      lies inside the MCAP's path;
    - an output would replace one of `inputs` (files the command reads: the scenario file, a
      mesh).

    `force` None: the command has no --force.
    """
    plan = OutputPlan(None, Path(parent), name, force, tuple(outputs), what)
    if out is not None:
        plan.folder, plan.existed = _check_folder(out, force, what, plan.outputs)
    folder = plan.folder.resolve() if plan.folder is not None else None
    if mcap is not None:
        if not str(mcap).strip():
            raise OutputError("--mcap: empty path (give a file, e.g. --mcap run.mcap)")
        path = _resolved_file(Path(mcap))
        if folder is not None:
            if path == folder:
                raise OutputError(f"--mcap {mcap}: is the {what} folder; give a file name")
            if folder.is_relative_to(path):
                raise OutputError(f"{what} {out}: lies inside --mcap's path {mcap}")
            if path.is_relative_to(folder):
                first = path.relative_to(folder).parts[0]
                if _planned(first, plan.outputs, prefixes):
                    raise OutputError(f"--mcap {mcap}: {first} in {what} {out} is one of "
                                      "this command's own outputs; give the MCAP log another "
                                      "name")
        plan.mcap = check_file_output(mcap, "--mcap", replace=force,
                                      previous=is_capsule_mcap,
                                      previous_name="an MCAP log written by capsule-sim",
                                      expected_bytes=mcap_bytes, planned_folder=folder)
    for source in inputs:
        if source is None or not Path(source).is_file():
            continue
        read = Path(source).resolve()
        if plan.mcap is not None and read == _resolved_file(plan.mcap):
            raise OutputError(f"--mcap {mcap}: is {source}, which this command reads")
        if folder is not None and read.is_relative_to(folder):
            first = read.relative_to(folder).parts[0]
            if _planned(first, plan.outputs, prefixes):
                raise OutputError(f"{what} {out}: would replace {source}, which this command "
                                  f"reads; copy it elsewhere or choose another {what}")
    return plan


def _planned(name: str, outputs, prefixes) -> bool:
    """Whether a folder's entry `name` is one a command writes there (its outputs, the
    temporary files of `write_atomic` and `check_room`)."""
    return (name in outputs or any(name.startswith(p) for p in prefixes)
            or (name.startswith(".") and name.endswith((PARTIAL, PROBE_NAME))))


def _resolved_file(path: Path) -> Path:
    """`path` with its folder's symbolic links resolved (the file itself is not a link)."""
    return Path(path).parent.resolve() / Path(path).name


def _kind(mode: int) -> str:
    """What kind of file `mode` is, in words."""
    for test, kind in ((stat.S_ISREG, "a file"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISLNK, "a symbolic link"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a regular file"


def _lstat(path: Path, what: str) -> os.stat_result | None:
    """os.lstat, or None when nothing is there."""
    try:
        return os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as e:
        raise OutputError(f"{what} {path}: cannot be examined ({_reason(e)})") from None


def _unwritable(folder: Path) -> str | None:
    """Why new files cannot be made in the existing folder `folder`, or None."""
    if os.access(folder, os.W_OK | os.X_OK):
        return None
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "Read-only file system"
    except OSError:
        pass
    return "Permission denied"


def _check_folder(out, force: bool | None, what: str, outputs: tuple[str, ...],
                  held: bool = False) -> tuple[Path, bool]:
    """(the folder `out`, whether it exists), refused with OutputError as `plan_outputs`
    says; nothing is changed on disk. `held`: this command holds the folder (the check
    under its lock)."""
    if str(out) == "":
        raise OutputError(f"{what}: empty path (give a folder, e.g. {what} runs/mine)")
    folder = Path(out)
    info = _lstat(folder, what)
    if info is not None and stat.S_ISLNK(info.st_mode) and not folder.exists():
        raise OutputError(f"{what} {folder}: a symbolic link to {os.readlink(folder)}, "
                          "which does not exist")
    if info is not None and not folder.is_dir():
        raise OutputError(f"{what} {folder}: exists and is not a folder "
                          f"({_kind(os.stat(folder).st_mode)})")
    if info is None:
        ancestor = folder.parent
        while _lstat(ancestor, what) is None and ancestor != ancestor.parent:
            ancestor = ancestor.parent
        if not ancestor.is_dir():
            raise OutputError(f"{what} {folder}: cannot create the output folder ({ancestor} "
                              "is not a folder)")
        reason = _unwritable(ancestor)
        if reason:
            raise OutputError(f"{what} {folder}: cannot create the output folder ({reason}: "
                              f"{ancestor})")
        return folder, False
    if not held and _held_elsewhere(folder):
        raise _in_use_error(what, folder)
    try:
        leftovers = _leftovers(outputs)
        entries = sorted(p.name for p in folder.iterdir() if p.name not in leftovers)
    except OSError as e:
        raise OutputError(f"{what} {folder}: cannot read the folder ({_reason(e)})") from None
    if entries and not force:
        shown = ", ".join(entries[:4]) + (", ..." if len(entries) > 4 else "")
        raise OutputError(f"{what} {folder}: folder exists and holds {shown}; choose "
                          "another folder" + ("" if force is None else
                                              ", or add --force to replace a previous "
                                              "run's outputs there"))
    for name in outputs if entries else ():
        entry = _lstat(folder / name, what)
        if entry is None:
            continue
        expected = stat.S_ISDIR if name in OUTPUT_FOLDERS else stat.S_ISREG
        if not expected(entry.st_mode):
            raise OutputError(f"{what} {folder}: its {name} is {_kind(entry.st_mode)}, not a "
                              "previous run's output; refusing to remove it (move it away "
                              f"or choose another {what})")
    reason = _unwritable(folder)
    if reason:
        raise OutputError(f"{what} {folder}: cannot write to the output folder ({reason})")
    return folder, True


def is_capsule_mcap(path: Path | str) -> bool:
    """Whether `path` starts as an MCAP file this simulator writes: the MCAP magic, then a
    header record naming MCAP_LIBRARY (so --force never replaces another program's log, or
    a file that is no MCAP at all)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return False
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            return False
        head = f.read(512)
    start = len(MCAP_MAGIC)
    if not head.startswith(MCAP_MAGIC) or len(head) < start + 13 or head[start] != 1:
        return False
    at = start + 9                                # opcode, then the record's length
    (profile,) = struct.unpack_from("<I", head, at)
    at += 4 + profile
    if at + 4 > len(head):
        return False
    (library,) = struct.unpack_from("<I", head, at)
    return head[at + 4:at + 4 + library] == MCAP_LIBRARY.encode()


def check_file_output(path, what: str, replace: bool | None = False, previous=None,
                      previous_name: str = "a previous output", expected_bytes: float = 0.0,
                      planned_folder: Path | None = None) -> Path:
    """The file `path` (named by the flag `what`) that a command will write, checked before
    anything is run; returns it as a Path. Refused with OutputError (one line):

    - an empty path, a folder, a symbolic link, anything not a regular file (a device, a
      named pipe: writing one could block forever or go nowhere);
    - an existing file unless `replace` (None: the command has no --force to offer), and
      even then unless `previous(path)` says it is a previous output of this kind
      (`previous_name`; no `previous`: none is replaced);
    - a folder that does not exist (unless it is `planned_folder`, which the command
      creates first) or cannot be written, or has less than `expected_bytes` free.
    """
    text = str(path)
    if not text.strip():
        raise OutputError(f"{what}: empty path (give a file, e.g. {what} run.mcap)")
    path = Path(path)
    info = _lstat(path, what)
    if info is not None:
        if stat.S_ISLNK(info.st_mode):
            raise OutputError(f"{what} {path}: is a symbolic link (to {os.readlink(path)}); "
                              "give the path of a file, not of a link")
        if stat.S_ISDIR(info.st_mode):
            raise OutputError(f"{what} {path}: is a folder; give a file name, e.g. "
                              f"{path / 'run.mcap'}")
        if not stat.S_ISREG(info.st_mode):
            raise OutputError(f"{what} {path}: not a regular file ({_kind(info.st_mode)}); "
                              "give the name of a file to write")
        if previous is None or not previous(path):
            raise OutputError(f"{what} {path}: file exists and is not {previous_name}; "
                              "it is never replaced (not even with --force): choose "
                              "another name")
        if not replace:
            raise OutputError(f"{what} {path}: file exists ({previous_name}); choose another "
                              "name" + (", or add --force to replace it"
                                        if replace is not None else ""))
        if not os.access(path, os.W_OK):
            raise OutputError(f"{what} {path}: cannot write there (Permission denied)")
    folder = path.parent
    if not folder.is_dir():
        if planned_folder is not None and folder.resolve() == planned_folder:
            return path  # the command's output folder, made before anything is written
        if os.path.lexists(folder):
            raise OutputError(f"{what} {path}: {folder} is not a folder")
        raise OutputError(f"{what} {path}: folder {folder} does not exist")
    reason = _unwritable(folder)
    if reason:
        raise OutputError(f"{what} {path}: cannot write there ({reason})")
    try:
        st = os.statvfs(folder)
        free = st.f_bavail * st.f_frsize
    except OSError:
        free = float("inf")
    if free < expected_bytes:
        raise OutputError(f"{what} {path}: {free / 1e6:.0f} MB free, but the file will take "
                          f"up to about {expected_bytes / 1e6:.0f} MB; free some space or "
                          "write it elsewhere")
    return path


def run_output_bytes(duration: float, log_period: float, recording: bool) -> float:
    """Bytes a run of `duration` will write (logs uncompressed, plus the recording)."""
    return (duration / log_period + 1) * SAMPLE_BYTES + WALL_MAP_BYTES + (
        RECORDING_BYTES + RECORDING_BYTES_PER_S * duration if recording else 0.0)


def check_room(folder: Path, needed_bytes: float, free_bytes=None) -> None:
    """Raises OutputError unless `folder` can be written and has room for `needed_bytes`
    (and SPARE_BYTES more). `free_bytes` overrides the measured free space (tests). The
    probe it writes is removed, also when writing it fails (a full disk creates the file,
    then refuses its bytes)."""
    probe = Path(folder) / PROBE_NAME
    try:
        try:
            probe.write_bytes(b"capsule-sim")
        finally:
            with contextlib.suppress(FileNotFoundError):
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
    temporary = path.with_name(f".{path.name}{PARTIAL}")
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


def is_disk_full(e: OSError) -> bool:
    return e.errno in (errno.ENOSPC, errno.EDQUOT)
