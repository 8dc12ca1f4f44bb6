"""The runs in processes of their own on this machine, or as tasks on a Dask cluster: each
run's wall-time limit, its crash or error as a failed row, and the signals that stop the
suite without losing the runs that finished."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection, wait

import numpy as np

from capsule_drake.app.benchmark.progress import RunsProgress
from capsule_drake.app.benchmark.task import PROGRESS_TOPIC, Task, failed_result, run_task
from capsule_drake.plugins import first_line, what_it_did


def default_run_timeout(duration: float) -> float:
    """The wall-time limit of a run of `duration` simulated seconds (s): three times the
    duration plus five minutes. The slowest navigator (the simulated operator with the arm)
    simulates about a second per wall second with two runs on two cores, and starting
    Python and Drake, building the station and a cold colon cache take up to a minute."""
    return 300.0 + 3.0 * float(duration)


class EngineError(Exception):
    """The suite's engine could not be used (a Dask scheduler that cannot be reached, an
    address that is not one); nothing was run."""


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
from capsule_drake.app.benchmark.pool import _worker_main
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


