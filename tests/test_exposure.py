"""Nothing listens beyond this machine unless asked (Meshcat, the browser operator's page,
the UDP bridge), and --host opens it deliberately."""

import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "capsule_drake.app.cli"]
LOOPBACK = {"127.0.0.1", "::1"}


def _sockets(process: subprocess.Popen, want, timeout: float = 120.0):
    """(ip, port, type) of the process's bound internet sockets, once `want(sockets)`."""
    start = time.monotonic()
    while True:
        assert process.poll() is None, process.communicate()
        sockets = set()
        for proc in [psutil.Process(process.pid)] + psutil.Process(process.pid).children(
                recursive=True):
            try:
                for c in proc.net_connections("inet"):
                    udp = c.type == socket.SOCK_DGRAM
                    if c.laddr and (c.status == psutil.CONN_LISTEN or udp):
                        sockets.add((c.laddr.ip, c.laddr.port, "udp" if udp else "tcp"))
            except psutil.NoSuchProcess:
                pass
        if want(sockets):
            return sockets
        assert time.monotonic() - start < timeout, sockets
        time.sleep(0.3)


def _run(args, tmp_path):
    return subprocess.Popen(CLI + args + ["--out", str(tmp_path / "run"), "--quiet"], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.slow
@pytest.mark.parametrize("args,kinds", [
    (["run", "--duration", "60"], {"tcp"}),                       # the recording's Meshcat
    (["run", "--duration", "60", "--meshcat", "--port", "0"], {"tcp"}),
    (["teleop", "--operator", "udp", "--port", "0", "--duration", "60"], {"tcp", "udp"}),
    (["teleop", "--operator", "browser", "--port", "0", "--duration", "60"], {"tcp"}),
])
def test_servers_listen_on_loopback_by_default(tmp_path, args, kinds):
    process = _run(args, tmp_path)
    try:
        sockets = _sockets(process, lambda found: kinds <= {kind for *_, kind in found})
        assert {ip for ip, *_ in sockets} <= LOOPBACK, sockets
    finally:
        process.kill()
        process.communicate()


@pytest.mark.slow
def test_host_opens_a_server_deliberately(tmp_path):
    # The check above can fail: with --host 0.0.0.0 Meshcat listens on every interface.
    process = _run(["run", "--duration", "60", "--meshcat", "--port", "0",
                    "--host", "0.0.0.0"], tmp_path)
    try:
        sockets = _sockets(process, lambda found: bool(found))
        assert "0.0.0.0" in {ip for ip, *_ in sockets}, sockets
    finally:
        process.kill()
        process.communicate()
