"""The navigation benchmark: a user's navigator through the plug-in interface on two colons
(locally and on a two-worker Dask cluster, the same table, each run's progress shown as it
goes), how a run ended (the time limit or a stall), and its one-line errors; a suite that
survives its runs (one that crashes its process, one that hangs), a signal, and its own
death, leaving no process behind."""

import contextlib
import csv
import io
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from capsule_drake.app.benchmark import (COLUMNS, TIERS, RowWriter, Task, breakdown,
                                         format_table,
                                         run_suite, run_task, summary, task_scenario,
                                         where_it_ended, wilson_interval, write_outputs)

# Short runs without the camera worker: a few simulated seconds each.
TEXT = "{capsule: {camera: {fps: 2.0, latency: 0.0}}}"


def _tasks():
    return [Task("plugins.navigators:creep", seed, duration=3.0, scenario_text=TEXT)
            for seed in (0, 1)]


@pytest.fixture(scope="module")
def finished_rows(tmp_path_factory):
    return tmp_path_factory.mktemp("partial") / "runs-as-finished.csv"


@pytest.fixture(scope="module")
def progress_lines():
    return io.StringIO()


@pytest.fixture(scope="module")
def local_results(finished_rows, progress_lines):
    # With its progress shown (a log, not a terminal: plain lines), every report printed.
    return run_suite(_tasks(), workers=2, engine="local", progress=True,
                     on_result=RowWriter(finished_rows), stream=progress_lines,
                     line_period=0.0)


def _progress_by_run(text):
    """{(navigator, seed): [(simulated time or None for building, "done" or line)]}."""
    runs = {}
    for line in text.splitlines():
        found = re.match(r"\[\s*\d+ s\] (?:done \d+/\d+: )?(\S+) seed (\d+): (.*)", line)
        if found:
            runs.setdefault((found[1], int(found[2])), []).append((line, found[3]))
    return runs


@pytest.mark.slow
def test_progress_shows_each_run_as_it_goes(local_results, progress_lines):
    text = progress_lines.getvalue()
    assert text.splitlines()[0].endswith("2 runs on 2 local worker processes; each reports "
                                         "once its process has started Python and Drake")
    for (navigator, seed), lines in _progress_by_run(text).items():
        said = [what for _, what in lines]
        assert said[0] == "building the station"
        # Reports of simulated time and place before the run's end line.
        running = [re.match(r"\s*([\d.]+) / 3 s simulated, (\w+) at (\d+) cm", what)
                   for what in said[1:-1]]
        assert running and all(running), said
        assert any(float(m[1]) < 3.0 for m in running) and {m[2] for m in running} == {"rectum"}
        assert said[-1].startswith("ended: time limit (rectum, at ")
        assert "done" in lines[-1][0]


@pytest.mark.slow
def test_each_local_run_has_a_process_of_its_own():
    # One worker, two runs: two processes (a worker kept each run's memory, 0.6-0.7 GB).
    # Only the processes are looked at: 0.2 s simulated each, not the table's 3 s.
    tasks = [Task("plugins.navigators:creep", seed, duration=0.2, scenario_text=TEXT)
             for seed in (0, 1)]
    results = run_suite(tasks, workers=1, engine="local", progress=False)
    assert len({r["worker_pid"] for r in results}) == 2


@pytest.mark.slow
def test_each_run_is_written_as_it_finishes(local_results, finished_rows):
    with open(finished_rows) as f:
        written = list(csv.DictReader(f))
    assert sorted(int(r["seed"]) for r in written) == [0, 1]
    assert list(written[0]) == list(COLUMNS)


@pytest.mark.slow
def test_a_user_navigator_runs_on_two_colons_and_gets_the_table(local_results, tmp_path):
    rows = [r["row"] for r in local_results]
    assert [row["seed"] for row in rows] == [0, 1]
    for row in rows:
        assert row["sim_time_s"] == pytest.approx(3.0)
        assert not row["reached_cecum"] and np.isnan(row["time_to_cecum_s"])
        # The EPM crept 3 cm: its path is that (plus the floor's rise), not zero.
        assert 0.029 < row["epm_path_m"] < 0.06
        assert 0.0 < row["coverage"] < 0.2  # the camera saw some of the rectum's wall
        # Still moving when the 3 s ran out: the time limit ended it, not a stall.
        assert re.fullmatch(r"time limit \(rectum, at \d+ cm\)", row["stuck_in"])
        assert np.isfinite(row["centring_error_deg"])
        # Per patch of the wall (physics/wall_pressure.py): the highest pressure one felt,
        # and the longest one spent above 330 kPa, within that above 4 kPa, within the run.
        assert row["site_peak_pressure_kPa"] > 4.0
        assert 0.0 <= row["site_injury_s"] <= row["site_ischaemia_s"] <= 3.0
    assert np.isfinite(summary(local_results)[0]["site_ischaemia_s"])
    paths = write_outputs(local_results, tmp_path)
    with open(paths["runs"]) as f:
        written = list(csv.DictReader(f))
    assert [int(r["seed"]) for r in written] == [0, 1] and list(written[0]) == list(COLUMNS)
    assert paths["progress"].stat().st_size > 10_000 and paths["segments"].exists()
    import json
    with open(paths["results"]) as f:
        saved = json.load(f)
    assert [r["row"]["seed"] for r in saved] == [0, 1] and len(saved[0]["curve"][0]) > 2
    table = format_table(summary(local_results), ["navigator", "runs", "reached_cecum"])
    assert "plugins.navigators:creep" in table and "0/2" in table


@pytest.mark.slow
def test_the_same_seeds_give_the_same_table_on_a_dask_cluster(local_results):
    lines = io.StringIO()
    results = run_suite(_tasks(), workers=2, engine="dask", progress=True, stream=lines,
                        line_period=0.0)
    # The runs' progress comes through the scheduler's events, as from the local pool.
    runs = _progress_by_run(lines.getvalue())
    assert sorted(runs) == [("plugins.navigators:creep", 0), ("plugins.navigators:creep", 1)]
    assert all(any("s simulated" in what for _, what in said) for said in runs.values())
    for a, b in zip(local_results, results):
        a = {k: v for k, v in a["row"].items() if k != "wall_time_s"}
        b = {k: v for k, v in b["row"].items() if k != "wall_time_s"}
        assert a.keys() == b.keys()
        for key in a:
            assert a[key] == b[key] or (a[key] != a[key] and b[key] != b[key]), key


def test_bad_navigators_get_one_line_errors():
    for navigator, message in (("wander", "navigator 'wander' is not one of autonomy-truth"),
                               ("nosuchmodule:f", "no module 'nosuchmodule' on the Python path"),
                               ("plugins.navigators:nothing", "has no function 'nothing'")):
        with pytest.raises(ValueError, match=message) as error:
            task_scenario(Task(navigator, 0, duration=0.1, scenario_text=TEXT))
        assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="epm.driver: navigator 'plugins.navigators:bad_port': "
                       "input port 'colon_centerline' is not one of") as error:
        run_task(Task("plugins.navigators:bad_port", 0, duration=0.1, scenario_text=TEXT))
    assert "\n" not in str(error.value)


# The follower on the sensors' pose estimate: the noise of the IMU and the Hall sensors
# (drawn from the scenario's random_seed) moves the EPM and so the capsule.
NOISY = ("{capsule: {camera: {fps: 2.0, latency: 0.0}, imu: {}, magnetic_array: {},"
         " localizer: {}}, epm: {driver: !LumenFollower {pose: sensors}}, random_seed: %d}")


@pytest.mark.slow
def test_the_benchmark_honours_the_random_seed():
    tasks = [Task("autonomy-truth", 0, duration=2.0, scenario_text=NOISY % seed)
             for seed in (1, 1, 2)]
    assert [task_scenario(task).random_seed for task in tasks] == [1, 1, 2]
    first, again, other = [run_task(task) for task in tasks]

    def row(result):
        return {k: v for k, v in result["row"].items() if k != "wall_time_s"}

    # The same seed: the same run, to the last bit.
    assert row(first) == row(again)
    assert first["curve"] == again["curve"]
    # Another seed: other noise, another run (measured on the rigid stand-in: the capsule
    # 0.6 mm apart along the centreline after 2 s; on the compliant wall, which the capsule
    # sticks to at first, 0.02 mm).
    assert first["curve"][0] == other["curve"][0]  # the same log times
    s_first, s_other = np.array(first["curve"][1]), np.array(other["curve"][1])
    assert s_first[0] == s_other[0]  # from the same start
    assert np.abs(s_first - s_other).max() > 5e-6, (s_first, s_other)


def test_benchmark_command_line_errors_are_one_line(capsys, monkeypatch, tmp_path):
    from capsule_drake.app.cli import main
    from capsule_drake.app.commands import benchmark as command

    def no_runs(*args, **kwargs):
        raise AssertionError("a bad command line must fail before any run starts")

    # A command line that got through would start the whole suite (10 colons x 600 s):
    # fail at once instead, writing nothing into the repository.
    monkeypatch.setattr(command, "run_suite", no_runs)
    monkeypatch.chdir(tmp_path)
    for argv, message in ((["--seeds", "x"], "--seeds 'x': expected"),
                          (["--navigators", "wander"], "navigator 'wander' is not one of"),
                          (["--scenario", "Nowhere"], "Nowhere"),
                          (["--run-timeout", "0"], "--run-timeout must be > 0"),
                          (["--run-timeout", "nan"], "--run-timeout must be > 0")):
        assert main(["benchmark", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_a_run_cut_off_by_time_says_so_and_a_stall_names_its_segment():
    times = np.arange(0.0, 600.0, 0.1)
    # Still advancing at the end: the time limit ended it.
    advancing = 0.05 + 0.001 * times
    assert where_it_ended(times, advancing, "descending", cut_by_time=True) == \
        "time limit (descending, at 65 cm)"
    # At its furthest point (within 1 cm) since 100 s: a stall, long before the limit.
    stalled = np.minimum(0.05 + 0.006 * times, 0.65) - 0.003 * np.sin(times) ** 2
    assert where_it_ended(times, stalled, "descending", cut_by_time=True) == "descending"
    # Moving back and forth within 1 cm of its furthest point until the end: a stall too.
    assert where_it_ended(times, 0.3 + 0.004 * np.sin(times), "sigmoid",
                          cut_by_time=True) == "sigmoid"
    # The window is 30 s: a run that got within 1 cm of its furthest point 29 s before the
    # end was still advancing; 31 s before, it had stalled.
    late = np.where(times < 571.0, 0.05 + 0.001 * times, 0.65)
    assert where_it_ended(times, late, "descending", cut_by_time=True).startswith("time limit")
    late = np.where(times < 569.0, 0.05 + 0.001 * times, 0.65)
    assert where_it_ended(times, late, "descending", cut_by_time=True) == "descending"
    assert where_it_ended(times, advancing, "descending", cut_by_time=False) == "descending"


class _Log:
    def __init__(self, rows):
        self._data = np.asarray(rows, dtype=float).T

    def data(self):
        return self._data


def test_detection_scores_compare_the_tracker_with_the_truth_sample_by_sample():
    from types import SimpleNamespace

    from capsule_drake.app.benchmark import _detection_scores
    lens = SimpleNamespace(width=300, height=400)  # diagonal 500 px
    truth = [[100, 100]] * 5 + [[np.nan, np.nan]]
    truth_visible = [[1]] * 5 + [[0]]
    # The truth is the image-side one (far_pixel, far_visible). Off by 5, 10, 15 px where
    # found; missed once; a detection where the truth sees no lumen counts toward the false
    # positives only.
    found = [[105, 100], [100, 110], [100, 85], [np.nan, np.nan], [100, 100], [50, 50]]
    found_visible = [[1], [1], [1], [0], [0], [1]]
    data = {"far_pixel": _Log(truth), "far_visible": _Log(truth_visible),
            "tracker_lumen_pixel": _Log(found), "tracker_lumen_visible": _Log(found_visible)}
    error, rate, false_positives = _detection_scores(lens, data)
    assert error == pytest.approx(100 * 10 / 500)
    assert rate == pytest.approx(3 / 5) and false_positives == pytest.approx(1.0)
    assert all(np.isnan(_detection_scores(None, data)))
    assert all(np.isnan(_detection_scores(lens, {k: data[k] for k in list(data)[:2]})))


# ---- A suite that survives its runs: a run whose process crashes or hangs, a signal, a
# parent killed outright. Each runs `capsule-sim benchmark` as a user would, one seed, 1 s
# simulated per run, the camera's frames drawn by its render process (latency > 0) so that
# every run has a process of its own and a child of that.

ROOT = Path(__file__).resolve().parents[1]
CAMERA = "{capsule: {camera: {fps: 2.0, latency: 0.05}}}"
CREEP, FAILS_LATER = "plugins.navigators:creep", "plugins.navigators:fails_later"
CRASHES, HANGS = "plugins.misbehaving:crashes", "plugins.misbehaving:hangs"
EXITS_LATER = "plugins.misbehaving:exits_later"
EXITS_IN_FACTORY = "plugins.misbehaving:exits_in_factory"


class _Suite:
    """`capsule-sim benchmark` in a process of its own, every process below it recorded
    (pid and start time) as it goes, its stdout and stderr in files."""

    def __init__(self, folder: Path, navigators, *flags):
        self.out = folder / "out"
        self.stdout, self.stderr = folder / "stdout.txt", folder / "stderr.txt"
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
        with open(self.stdout, "w") as out, open(self.stderr, "w") as err:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "capsule_drake.app.cli", "benchmark", "--seeds", "0",
                 "--navigators", ",".join(navigators), "--duration", "1",
                 "--scenario-text", CAMERA, "--out", str(self.out), *flags],
                stdout=out, stderr=err, stdin=subprocess.DEVNULL, env=env, cwd=folder)
        self.seen: dict[int, psutil.Process] = {}
        self.commands: dict[int, str] = {}
        self._done = threading.Event()
        self._watcher = threading.Thread(target=self._watch, daemon=True)
        self._watcher.start()

    def _watch(self):
        parent = psutil.Process(self.process.pid)
        while not self._done.is_set():
            try:
                children = parent.children(recursive=True)
            except psutil.NoSuchProcess:
                return
            for child in children:
                self.seen.setdefault(child.pid, child)
                if not self.commands.get(child.pid):
                    with contextlib.suppress(psutil.Error):
                        self.commands[child.pid] = " ".join(child.cmdline())
            time.sleep(0.1)

    def render_processes(self):
        """The camera render processes seen below the suite (its runs' children)."""
        return [pid for pid, command in list(self.commands.items())
                if "capsule_drake.capsule.render_process" in command]

    def rows_as_finished(self):
        path = self.out / "runs-as-finished.csv"
        if not path.exists():
            return []
        with open(path) as f:
            return list(csv.DictReader(f))

    def wait_for(self, condition, timeout: float, what: str):
        end = time.monotonic() + timeout
        while not condition():
            assert self.process.poll() is None, f"the suite ended before {what}: {self.err()}"
            assert time.monotonic() < end, f"no {what} within {timeout:.0f} s: {self.err()}"
            time.sleep(0.2)

    def finish(self, timeout: float) -> int:
        try:
            return self.process.wait(timeout=timeout)
        finally:
            self._done.set()
            self._watcher.join()

    def left_behind(self, grace: float = 3.0):
        """The processes that were below the suite and are still alive `grace` s after it
        ended (zombies waiting for init count as gone)."""
        end = time.monotonic() + grace
        while True:
            alive = []
            for process in self.seen.values():
                with contextlib.suppress(psutil.Error):
                    if process.is_running() and process.status() != psutil.STATUS_ZOMBIE:
                        alive.append(process)
            if not alive or time.monotonic() > end:
                return [(p.pid, p.cmdline()) for p in alive]
            time.sleep(0.2)

    def clean_up(self):
        """Kills whatever is left (a test that failed must not leave a hung suite)."""
        self._done.set()
        targets = list(self.seen.values())
        if self.process.poll() is None:
            targets.insert(0, self.process)
        for process in targets:
            with contextlib.suppress(psutil.Error, ProcessLookupError):
                process.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(timeout=10)

    def err(self) -> str:
        return self.stderr.read_text()

    def rows(self):
        with open(self.out / "runs.csv") as f:
            return list(csv.DictReader(f))


@pytest.fixture
def suites():
    started = []
    yield lambda *args: started.append(_Suite(*args)) or started[-1]
    for suite in started:
        suite.clean_up()


@pytest.mark.slow
def test_a_run_that_crashes_or_hangs_is_a_failed_row_and_the_suite_goes_on(tmp_path, suites):
    # Before: the crash ended the suite (exit 70, BrokenProcessPool) with none of the runs
    # saved, and the hang held it for ever.
    # The limit leaves a good run room: 10-20 s each, three at once on two cores (up to 70 s
    # on two cores shared with other work: 20 s to start Python and Drake, 40 s to build;
    # the suite's CI runs alone).
    suite = suites(tmp_path, [HANGS, CREEP, FAILS_LATER, CRASHES], "--workers", "3",
                   "--run-timeout", "45")
    assert suite.finish(timeout=600) == 1, suite.err()
    rows = suite.rows()
    assert [row["navigator"] for row in rows] == [HANGS, CREEP, FAILS_LATER, CRASHES]
    hang, creep, fails_later, crash = rows
    assert [row["status"] for row in rows] == ["failed", "finished", "failed", "failed"]
    assert hang["error"] == "timed out after 45 s" and 45 <= float(hang["wall_time_s"]) < 75
    assert crash["error"] == "crashed: worker exited with signal 9 (SIGKILL)"
    # The good run as it would be alone; the navigator that raised inside the simulation
    # failed its run.
    assert creep["error"] == "" and float(creep["sim_time_s"]) == pytest.approx(1.0)
    assert creep["stuck_in"].startswith("time limit (rectum, at ")
    assert fails_later["error"] == (f"simulation error at t = 0.500 s: navigator "
                                    f"'{FAILS_LATER}' raised ZeroDivisionError: the navigator "
                                    "divided by zero")
    assert sorted(row["navigator"] for row in suite.rows_as_finished()) == sorted(
        row["navigator"] for row in rows)
    for name in ("summary.csv", "progress.png", "segments.png", "results.json"):
        assert (suite.out / name).exists(), name
    err = suite.err()
    assert "Traceback" not in err and err.splitlines()[-1] == (
        f"capsule-sim: 3 of 4 runs failed (the error column says why): {HANGS} seed 0, "
        f"{FAILS_LATER} seed 0, {CRASHES} seed 0")
    assert suite.render_processes()  # each run had its camera's render process
    assert suite.left_behind() == []


@pytest.mark.slow
def test_a_suite_whose_navigators_raise_or_exit_inside_their_runs_fails(tmp_path, suites):
    # Before: both runs were "finished" rows and the suite exited 0, where `run` with either
    # navigator exits 1.
    suite = suites(tmp_path, [FAILS_LATER, EXITS_LATER], "--workers", "2")
    assert suite.finish(timeout=600) == 1, suite.err()
    fails_later, exits_later = suite.rows()
    assert [fails_later["status"], exits_later["status"]] == ["failed", "failed"]
    assert fails_later["error"] == (f"simulation error at t = 0.500 s: navigator "
                                    f"'{FAILS_LATER}' raised ZeroDivisionError: the navigator "
                                    "divided by zero")
    assert exits_later["error"] == (f"simulation error at t = 0.500 s: navigator "
                                    f"'{EXITS_LATER}' exited (SystemExit: 0)")
    assert float(exits_later["sim_time_s"]) == pytest.approx(0.5)
    err = suite.err()
    assert "Traceback" not in err and err.splitlines()[-1] == (
        f"capsule-sim: 2 of 2 runs failed (the error column says why): {FAILS_LATER} seed 0, "
        f"{EXITS_LATER} seed 0")
    assert suite.left_behind() == []


@pytest.mark.slow
def test_a_navigator_that_exits_fails_its_run_on_a_dask_cluster():
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    # Before: the exit in the factory killed the Dask worker ("crashed: the Dask worker
    # running it died"), and the exit inside the simulation was a finished row.
    tasks = [Task(navigator, 0, duration=1.0, scenario_text=TEXT)
             for navigator in (EXITS_IN_FACTORY, EXITS_LATER)]
    in_factory, later = (r["row"] for r in run_suite(tasks, workers=2, engine="dask",
                                                     progress=False))
    assert in_factory["status"] == "failed" and in_factory["error"] == (
        f"raised ScenarioError: scenario: epm.driver: navigator '{EXITS_IN_FACTORY}' failed "
        "to build its system (SystemExit: 0)")
    assert later["status"] == "failed" and later["error"] == (
        f"simulation error at t = 0.500 s: navigator '{EXITS_LATER}' exited (SystemExit: 0)")


@pytest.mark.slow
def test_ctrl_c_during_a_hang_keeps_the_finished_rows_and_leaves_no_process(tmp_path, suites):
    # Before: "interrupted", and the suite went on waiting for the hung run (a second
    # Ctrl-C too).
    # The default limit, 303 s for 1 s simulated, leaves the hung run to the Ctrl-C.
    suite = suites(tmp_path, [HANGS, CREEP, FAILS_LATER, CRASHES], "--workers", "3")
    suite.wait_for(lambda: len(suite.rows_as_finished()) == 3, 300, "three finished runs")
    time.sleep(1.0)
    suite.process.send_signal(signal.SIGINT)
    assert suite.finish(timeout=30) == 130, suite.err()
    assert suite.err().splitlines()[-1] == "capsule-sim: interrupted (SIGINT)"
    rows = suite.rows()
    assert [row["navigator"] for row in rows] == [CREEP, FAILS_LATER, CRASHES]
    assert [row["status"] for row in rows] == ["finished", "failed", "failed"]
    assert (suite.out / "results.json").exists() and (suite.out / "summary.csv").exists()
    assert len(suite.render_processes()) >= 1
    assert suite.left_behind() == []


@pytest.mark.slow
def test_sigterm_stops_the_runs_at_once_and_keeps_the_finished_row(tmp_path, suites):
    # Before: SIGTERM waited for the running run (here for ever) and then dropped its row.
    suite = suites(tmp_path, [HANGS, CREEP], "--workers", "2")
    suite.wait_for(lambda: len(suite.rows_as_finished()) == 1, 300, "a finished run")
    suite.process.send_signal(signal.SIGTERM)
    assert suite.finish(timeout=30) == 143, suite.err()
    assert [row["navigator"] for row in suite.rows()] == [CREEP]
    assert suite.left_behind() == []


@pytest.mark.slow
def test_a_suite_killed_outright_leaves_no_process_behind(tmp_path, suites):
    suite = suites(tmp_path, [HANGS], "--workers", "1")
    # Its run hangs in the simulation, beside the camera's render process.
    suite.wait_for(lambda: suite.render_processes() and "s simulated" in suite.err(), 300,
                   "hung run")
    time.sleep(1.0)
    suite.process.kill()
    suite.finish(timeout=10)
    assert suite.left_behind(grace=20.0) == []


@pytest.mark.slow
def test_an_unreachable_dask_scheduler_is_one_line(tmp_path):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PYTHONPATH=str(ROOT), DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="2s")
    for address, message in ((f"127.0.0.1:{port}", "cannot reach a Dask scheduler at "),
                              ("nonsense:::", "cannot reach a Dask scheduler at ")):
        out = tmp_path / f"out-{port}-{len(address)}"
        done = subprocess.run(
            [sys.executable, "-m", "capsule_drake.app.cli", "benchmark", "--seeds", "0",
             "--navigators", "autonomy-truth", "--duration", "1", "--engine", "dask",
             "--address", address, "--out", str(out), "--quiet"],
            capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("capsule-sim: error: --address: ") \
            and message in lines[0], done.stderr
        assert not out.exists()  # nothing was run, nothing written


def test_the_intubation_interval_is_wilsons():
    """Newcombe (Statistics in Medicine 17:857, 1998), Table I, the Wilson score interval
    without continuity correction: 81/263 -> 0.2553-0.3662, 15/148 -> 0.0624-0.1605,
    0/20 -> 0-0.1611, 1/29 -> 0.0061-0.1718; and n/n mirrors 0/n."""
    for (k, n), (low, high) in {(81, 263): (0.2553, 0.3662), (15, 148): (0.0624, 0.1605),
                                (0, 20): (0.0, 0.1611), (1, 29): (0.0061, 0.1718)}.items():
        assert wilson_interval(k, n) == pytest.approx((low, high), abs=6e-5)
    low, high = wilson_interval(20, 20)
    assert (low, high) == pytest.approx((1 - 0.1611, 1.0), abs=6e-5)


@pytest.mark.slow
def test_the_population_tier_draws_its_patients():
    """--tier population: the seeds 1000-1029 and a colon drawn from the population; the
    standard tier's colons are the procedural ones of seeds 0-9."""
    seeds, text = TIERS["population"]
    assert seeds == "1000-1029"
    scenario = task_scenario(Task("autonomy-truth", 1000, 5.0, tier_text=text))
    assert scenario.colon.population is not None and scenario.colon.seed == 1000
    assert scenario.colon.lumen is not None
    seeds, text = TIERS["standard"]
    assert seeds == "0-9" and task_scenario(Task("autonomy-truth", 3, 5.0,
                                                 tier_text=text)).colon.population is None


def test_the_breakdown_counts_each_group_of_patients():
    """Nine runs of one navigator: the groups by sigmoid, sex and length tercile count the
    runs they hold, each with its Wilson interval and the mean time of those that arrived;
    runs on colons not drawn from the population give no breakdown."""
    patients = ["female, redundant sigmoid", "male, normal sigmoid", "male, normal sigmoid"] * 3
    lengths = [120.0, 125.0, 130.0, 150.0, 151.0, 152.0, 180.0, 185.0, 190.0]
    reached = [True, True, False, True, True, True, False, True, True]
    results = [{"row": {"navigator": "n", "seed": k, "colon_cm": lengths[k],
                        "patient": patients[k], "reached_cecum": reached[k],
                        "time_to_cecum_s": 100.0 + k if reached[k] else float("nan")}}
               for k in range(9)]
    rows = {row["group"]: row for row in breakdown(results)}
    assert rows["all"]["reached_cecum"] == "7/9"
    assert rows["redundant sigmoid"]["reached_cecum"] == "2/3"   # runs 0, 3, 6: 6 failed
    assert rows["female"]["reached_cecum"] == rows["redundant sigmoid"]["reached_cecum"]
    assert rows["male"]["reached_cecum"] == "5/6"
    thirds = [name for name in rows if name.startswith("length")]
    assert [rows[name]["reached_cecum"] for name in thirds] == ["2/3", "3/3", "2/3"]
    assert rows["all"]["time_to_cecum_s"] == pytest.approx(np.mean([100, 101, 103, 104, 105,
                                                                     107, 108]), abs=0.05)
    low, high = (float(x) for x in rows["all"]["cecum_95ci"].strip("[]").split(","))
    assert (low, high) == pytest.approx(wilson_interval(7, 9), abs=0.005)
    # A failed run's row (its process crashed) has no patient and no length: counted in
    # "all" only.
    results.append({"row": {"navigator": "n", "seed": 9, "colon_cm": float("nan"),
                            "patient": float("nan"), "reached_cecum": False,
                            "time_to_cecum_s": float("nan")}})
    rows = {row["group"]: row for row in breakdown(results)}
    assert rows["all"]["reached_cecum"] == "7/10" and rows["male"]["reached_cecum"] == "5/6"
    for r in results:
        r["row"]["patient"] = ""
    assert breakdown(results) == []

