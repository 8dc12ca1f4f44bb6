"""The colon cache's folder ($CAPSULE_DRAKE_CACHE, else ~/.cache/capsule_drake) as a
careless user or a hostile machine gives it (anatomy/cache.py, `cache_base`):
- a variable that names a file, a device or a path through a file is a mistake in it: every
  command that builds colons refuses it in one line naming the variable and the path, exit
  2, before anything is made;
- a folder that cannot be written (a read-only disk, a full one) is the machine's state:
  the run goes on without the cache, with one warning line, its colon built in a temporary
  folder that is removed when it ends; if no temporary folder can be written either, one
  line and exit 2;
- a disk that fills while a colon is written into the cache is one line naming the cache,
  not an internal error.
"""

import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from capsule_drake.anatomy import cache
from capsule_drake.app.cli import main as cli_main
from test_bad_inputs import _assert_one_line, _tmpfs

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "capsule_drake.app.cli"]
CACHE_VARIABLE = "CAPSULE_DRAKE_CACHE"

# Each command that builds a colon, with a short run of it.
COMMANDS = {
    "run": ["run", "--duration", "0.1", "--no-recording", "--quiet", "--out", "{out}"],
    "record": ["record", "--duration", "0.1", "--quiet", "--out", "{out}"],
    "teleop": ["teleop", "--duration", "0.1", "--quiet", "--out", "{out}"],
    "benchmark": ["benchmark", "--seeds", "0", "--duration", "0.1", "--quiet", "--out",
                  "{out}"],
    "eval-lumen": ["eval-lumen", "--frames", "1", "--colons", "1", "--quiet", "--out",
                   "{out}"],
}


def _refused(monkeypatch, capsys, tmp_path, value, culprit, verb="run"):
    monkeypatch.setenv(CACHE_VARIABLE, str(value))
    out = tmp_path / "out"
    argv = [a.replace("{out}", str(out)) for a in COMMANDS[verb]]
    code = cli_main(argv)
    line = _assert_one_line(code, capsys.readouterr().err,
                            re.escape(f"{CACHE_VARIABLE}={value}: ") + culprit)
    assert code == 2, line
    assert not out.exists()  # refused before anything was made
    return line


@pytest.mark.parametrize("verb", list(COMMANDS))
def test_a_cache_variable_naming_a_file_is_refused_in_one_line(verb, tmp_path, monkeypatch,
                                                                capsys):
    named = tmp_path / "cache.txt"
    named.write_text("notes")
    line = _refused(monkeypatch, capsys, tmp_path, named,
                    r"cannot be a folder \(it is a file\)", verb)
    assert f"point {CACHE_VARIABLE} at a folder" in line
    assert named.read_text() == "notes"


def test_a_cache_variable_through_a_file_is_refused(tmp_path, monkeypatch, capsys):
    named = tmp_path / "cache.txt"
    named.write_text("notes")
    _refused(monkeypatch, capsys, tmp_path, named / "capsule",
             re.escape(f"cannot be a folder ({named} is a file)"))


def test_a_cache_variable_naming_a_device_is_refused(tmp_path, monkeypatch, capsys):
    _refused(monkeypatch, capsys, tmp_path, "/dev/null",
             r"cannot be a folder \(it is not a folder\)")


@pytest.fixture
def fresh_cache(monkeypatch, tmp_path):
    """Each value of the variable checked anew; a temporary cache made by a fallback is
    removed after the test (the process's exit would remove it otherwise)."""
    monkeypatch.setattr(cache, "_BASES", {})
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "temporary"))
    (tmp_path / "temporary").mkdir()
    yield tmp_path / "temporary"


def _read_only_folder(stack, tmp_path):
    """A read-only folder: a read-only tmpfs where the tests run as root (root writes
    through permissions), else a folder without write permission."""
    folder = stack.enter_context(_tmpfs(tmp_path / "ro", "1m", read_only=True))
    if folder is None:
        folder = tmp_path / "ro"
        folder.chmod(0o555)
    return folder


def test_a_read_only_cache_folder_runs_without_the_cache_with_one_warning(
        tmp_path, monkeypatch, fresh_cache, caplog):
    import contextlib

    with contextlib.ExitStack() as stack:
        folder = _read_only_folder(stack, tmp_path)
        monkeypatch.setenv(CACHE_VARIABLE, str(folder))
        with caplog.at_level(logging.WARNING, logger="capsule_drake.anatomy"):
            base = cache.cache_base()
            assert cache.cache_base() == base  # checked once
        warnings = [r.getMessage() for r in caplog.records]
        assert len(warnings) == 1, warnings
        assert f"{CACHE_VARIABLE}={folder}: cannot be written (" in warnings[0]
        assert "running without the cache" in warnings[0]
        # A temporary folder, given to the processes this one starts.
        assert base.parent == fresh_cache and (base / "colon").is_dir()
        assert os.environ[CACHE_VARIABLE] == str(base)
        assert cache.default_cache_root() == base / "colon"
        assert not any(folder.iterdir())


def test_a_full_cache_disk_runs_without_the_cache_with_one_warning(
        tmp_path, monkeypatch, fresh_cache, caplog):
    with _tmpfs(tmp_path / "full", "1m") as full:
        if full is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        with open(full / "filler", "wb") as f, pytest.raises(OSError):
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        monkeypatch.setenv(CACHE_VARIABLE, str(full))
        with caplog.at_level(logging.WARNING, logger="capsule_drake.anatomy"):
            base = cache.cache_base()
        warnings = [r.getMessage() for r in caplog.records]
        assert len(warnings) == 1 and "No space left on device" in warnings[0], warnings
        assert base.parent == fresh_cache


def test_a_cache_disk_with_too_little_room_runs_without_the_cache(tmp_path, monkeypatch,
                                                                   fresh_cache, caplog):
    with _tmpfs(tmp_path / "small", "2m") as small:
        if small is None:
            pytest.skip("needs root to mount a small tmpfs")
        monkeypatch.setenv(CACHE_VARIABLE, str(small))
        with caplog.at_level(logging.WARNING, logger="capsule_drake.anatomy"):
            base = cache.cache_base()
        assert base.parent == fresh_cache
        assert re.search(r"\d MB free, less than the 100 MB a colon's files need",
                         caplog.records[0].getMessage())


def test_no_writable_cache_and_no_temporary_folder_is_one_line(tmp_path, monkeypatch,
                                                               fresh_cache, capsys):
    import contextlib

    with contextlib.ExitStack() as stack:
        folder = _read_only_folder(stack, tmp_path)
        monkeypatch.setattr(tempfile, "tempdir", str(folder))
        monkeypatch.setenv(CACHE_VARIABLE, str(folder))
        code = cli_main(["run", "--duration", "0.1", "--no-recording", "--quiet", "--out",
                         str(tmp_path / "out")])
        line = _assert_one_line(code, capsys.readouterr().err,
                                re.escape(f"{CACHE_VARIABLE}={folder}: cannot be written (")
                                + r".*nor can a temporary folder")
        assert code == 2, line


def test_a_disk_that_fills_while_a_colon_is_cached_is_one_line(tmp_path):
    with _tmpfs(tmp_path / "small", "1m") as small:
        if small is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")

        def write(folder):
            (folder / "colon_visual.obj").write_bytes(b"v 0 0 0\n" * 400_000)  # 3.2 MB

        with pytest.raises(cache.CacheError) as error:
            cache.build_once(small / "colon" / "abc", write)
        message = str(error.value)
        assert "\n" not in message and str(small / "colon") in message
        assert "No space left on device" in message and CACHE_VARIABLE in message
        assert [p.name for p in (small / "colon").iterdir()] == []  # nothing half written


@pytest.mark.slow
def test_a_run_on_a_read_only_cache_completes_and_leaves_nothing_behind(tmp_path):
    """End to end, in a process of its own: the Default's colon is built in a temporary
    folder (one warning line on stderr), the run exits 0, and the temporary folder is gone
    when it has ended."""
    import contextlib

    with contextlib.ExitStack() as stack:
        folder = _read_only_folder(stack, tmp_path)
        temporary = tmp_path / "temporary"
        temporary.mkdir()
        out = tmp_path / "out"
        done = subprocess.run(
            CLI + ["run", "--duration", "0.1", "--quiet", "--out", str(out)], cwd=REPO,
            env=dict(os.environ, **{CACHE_VARIABLE: str(folder), "TMPDIR": str(temporary)}),
            capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stderr
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and "running without the cache" in lines[0], done.stderr
        assert (out / "metrics.json").is_file() and (out / "recording.html").is_file()
        assert not any(folder.iterdir())
        assert not list(temporary.glob("capsule_drake-cache-*"))
