"""Reference client of the UDP haptic bridge: replays a recorded stylus trajectory.

    python -m capsule_drake.teleop.udp_client TRAJECTORY.csv --host 127.0.0.1 --port N \\
        [--rate 1000] [--log replies.csv]

TRAJECTORY.csv has a header row and the columns t (s), x, y, z (m, device frame D: x right,
y up, z toward the operator, origin at the workspace centre), qw, qx, qy, qz (orientation,
unit quaternion) and buttons (bit 0 clutch, bit 1 mode). Row i is sent as sequence number
i + 1 at its timestamp (relative to the first row) or, with --rate, at i / rate; the client
time in each packet is the wall-clock time of sending since the replay started. Force
replies are read without blocking and written to --log as CSV (wall time since the start,
answered seq, server sim time, fx, fy, fz, status).

The wire format is docs/udp_protocol.md; `StylusClient` is the same client as a library.
"""

import argparse
import select
import socket
import sys
import time

import numpy as np

from capsule_drake.teleop.udp import ForcePacket, decode_force, pack_stylus

TRAJECTORY_COLUMNS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz", "buttons")
REPLY_LOG_COLUMNS = ("wall_time", "seq", "sim_time", "fx", "fy", "fz", "status")


class StylusClient:
    """A device-side UDP endpoint: sends stylus packets, reads force replies.

    The socket is non-blocking and connected to the server, so only the server's datagrams
    are received. Sequence numbers start at `first_seq` and wrap at 2**32. Network errors
    (e.g. ECONNREFUSED while no server listens) are counted in `errors`, never raised.

    Args:
        host, port: the server (UdpHapticDevice.address()).
        first_seq: sequence number of the first `send`.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, first_seq: int = 1):
        if not 0 < port <= 65535:
            raise ValueError(f"client port {port} must be in [1, 65535]")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self._socket.connect((host, port))
        self.seq = int(first_seq) % (1 << 32)  # the next send's sequence number
        self.sent = 0  # datagrams handed to the OS (send and send_raw)
        self.errors = 0  # send/receive errors
        self.bad_replies = 0  # datagrams that were not valid force packets
        self._start = time.monotonic()

    def address(self) -> tuple[str, int]:
        """The client's own (host, port)."""
        return self._socket.getsockname()[:2]

    def send(self, position, quaternion=(1.0, 0.0, 0.0, 0.0), buttons: int = 0,
             client_time: float | None = None) -> int:
        """Sends one stylus packet; returns its sequence number. client_time defaults to
        the seconds since this client was made."""
        seq = self.seq
        if client_time is None:
            client_time = time.monotonic() - self._start
        self.send_raw(pack_stylus(seq, client_time, position, quaternion, int(buttons)))
        self.seq = (seq + 1) % (1 << 32)
        return seq

    def send_raw(self, data: bytes) -> bool:
        """Sends `data` as one datagram, as is (for tests of bad packets); False on error."""
        try:
            self._socket.send(data)
        except OSError:
            self.errors += 1
            return False
        self.sent += 1
        return True

    def receive(self, timeout: float = 0.0) -> list[ForcePacket]:
        """All force replies waiting, oldest first. With timeout > 0 and none waiting, waits
        up to `timeout` s for the first."""
        replies = []
        if timeout > 0.0:
            select.select([self._socket], [], [], timeout)
        while True:
            try:
                data = self._socket.recv(65536)
            except BlockingIOError:
                return replies
            except OSError:
                self.errors += 1
                continue
            packet, _ = decode_force(data)
            if packet is None:
                self.bad_replies += 1
            else:
                replies.append(packet)

    def close(self) -> None:
        self._socket.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def load_trajectory(path) -> np.ndarray:
    """(N, 9) rows t, x, y, z, qw, qx, qy, qz, buttons of a trajectory CSV (header checked)."""
    with open(path) as f:
        header = f.readline().strip().split(",")
    if tuple(h.strip() for h in header) != TRAJECTORY_COLUMNS:
        raise ValueError(f"trajectory {path}: header {header} must be "
                         f"{','.join(TRAJECTORY_COLUMNS)}")
    rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if rows.shape[1] != len(TRAJECTORY_COLUMNS) or len(rows) == 0:
        raise ValueError(f"trajectory {path}: needs rows of {len(TRAJECTORY_COLUMNS)} values")
    if not np.all(np.diff(rows[:, 0]) >= 0.0):
        raise ValueError(f"trajectory {path}: t must not decrease")
    return rows


def save_trajectory(path, rows) -> None:
    """Writes (N, 9) rows as a trajectory CSV (t to 1 us, pose to 1e-6, buttons integer)."""
    rows = np.asarray(rows, dtype=float)
    with open(path, "w", newline="\n") as f:
        f.write(",".join(TRAJECTORY_COLUMNS) + "\n")
        for row in rows:
            values = (f"{v:.6f}" for v in row[:8])
            f.write(",".join("0.000000" if v == "-0.000000" else v for v in values)
                    + f",{int(row[8])}\n")


def replay(client: StylusClient, trajectory: np.ndarray, rate: float | None = None,
           linger: float = 0.2) -> tuple[int, list[tuple[float, ForcePacket]]]:
    """Sends the trajectory's rows on schedule (their t, or i / rate) and collects replies
    until `linger` s after the last send. Returns (packets sent, [(wall time, reply)])."""
    if rate is not None:
        schedule = np.arange(len(trajectory)) / rate
    else:
        schedule = trajectory[:, 0] - trajectory[0, 0]
    replies = []
    start = time.monotonic()
    sent = 0
    for due, row in zip(schedule, trajectory):
        delay = start + due - time.monotonic()
        if delay > 0.0:
            time.sleep(delay)
        now = time.monotonic() - start
        client.send(row[1:4], row[4:8], int(row[8]), client_time=now)
        sent += 1
        replies.extend((now, reply) for reply in client.receive())
    end = time.monotonic() + linger
    while (remaining := end - time.monotonic()) > 0.0:
        for reply in client.receive(timeout=remaining):
            replies.append((time.monotonic() - start, reply))
    return sent, replies


def write_reply_log(path, replies: list[tuple[float, ForcePacket]]) -> None:
    """Writes replies as CSV with the columns REPLY_LOG_COLUMNS."""
    with open(path, "w", newline="\n") as f:
        f.write(",".join(REPLY_LOG_COLUMNS) + "\n")
        for wall_time, r in replies:
            f.write(f"{wall_time:.6f},{r.seq},{r.sim_time:.6f},{r.force[0]:.9g},"
                    f"{r.force[1]:.9g},{r.force[2]:.9g},{r.status}\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m capsule_drake.teleop.udp_client",
        description="Replay a stylus trajectory to the simulator's UDP haptic bridge.")
    parser.add_argument("trajectory", help="CSV: " + ",".join(TRAJECTORY_COLUMNS))
    parser.add_argument("--host", default="127.0.0.1", help="server address")
    parser.add_argument("--port", type=int, required=True, help="server UDP port")
    parser.add_argument("--rate", type=float, default=None,
                        help="send at this rate (Hz) instead of the trajectory's timestamps")
    parser.add_argument("--log", default=None, help="write the force replies to this CSV")
    parser.add_argument("--linger", type=float, default=0.2,
                        help="seconds to keep reading replies after the last send")
    args = parser.parse_args(argv)
    if args.rate is not None and not args.rate > 0.0:
        parser.error(f"--rate {args.rate} must be positive")
    trajectory = load_trajectory(args.trajectory)
    with StylusClient(args.host, args.port) as client:
        sent, replies = replay(client, trajectory, args.rate, args.linger)
        errors = client.errors
    if args.log:
        write_reply_log(args.log, replies)
    last = replies[-1][1].seq if replies else None
    print(f"sent {sent} stylus packets ({errors} socket errors), received {len(replies)} "
          f"force replies (last answered seq {last})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
