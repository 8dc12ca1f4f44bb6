"""The UDP haptic bridge over loopback: codec, replay into a running simulation, bad packets,
floods, link loss, force saturation.

Regenerate the recorded trajectory with `python tests/test_udp_bridge.py`.
"""

import gc
import math
import select
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

from capsule_drake.teleop import udp_client
from capsule_drake.teleop.udp import (FORCE_SIZE, STATS_NAMES, STATUS_FORCE_INVALID,
                                      STATUS_LINK_OK, STATUS_SATURATED, STYLUS_SIZE,
                                      UdpBridgeConfig, UdpHapticDevice, decode_stylus,
                                      pack_force, pack_stylus, saturate_force,
                                      sequence_is_newer, unpack_force, unpack_stylus)
from capsule_drake.teleop.udp_client import StylusClient, load_trajectory

TRAJECTORY = Path(__file__).parent / "data" / "stylus_trajectory.csv"
PERIOD = 0.001
FORCE = np.array([0.5, -1.0, 0.25])  # N, inside the 3.3 N limit


def lissajous_trajectory(duration: float = 3.0, rate: float = 1000.0) -> np.ndarray:
    """A smooth stylus motion inside the Touch's 160 x 120 x 70 mm workspace: a Lissajous
    figure in position, a slow yaw (about y_D) and pitch (about x_D) wobble, the clutch held
    for 0.5-2.5 s and the mode button for 1.0-1.5 s. Rows as in a trajectory CSV."""
    t = np.arange(round(duration * rate) + 1) / rate
    x = 0.05 * np.sin(2 * np.pi * 0.5 * t)
    y = 0.03 * np.sin(2 * np.pi * 0.75 * t + np.pi / 3)
    z = 0.02 * np.sin(2 * np.pi * 1.0 * t)
    half_yaw = 0.5 * 0.3 * np.sin(2 * np.pi * 0.5 * t)
    half_pitch = 0.5 * 0.2 * np.sin(2 * np.pi * 0.25 * t)
    cy, sy, cx, sx = np.cos(half_yaw), np.sin(half_yaw), np.cos(half_pitch), np.sin(half_pitch)
    # q_yaw (about y) * q_pitch (about x), Hamilton product written out.
    q = np.stack([cy * cx, cy * sx, sy * cx, -sy * sx], axis=1)
    buttons = (((t >= 0.5) & (t < 2.5)) * 1) | (((t >= 1.0) & (t < 1.5)) * 2)
    return np.column_stack([t, x, y, z, q, buttons])


class Bench:
    """UdpHapticDevice <- ConstantVectorSource(force), a 1 kHz logger on `stylus`, a
    simulator advanced one server tick at a time."""

    def __init__(self, force=FORCE, **config):
        builder = DiagramBuilder()
        self.config = UdpBridgeConfig(period=PERIOD, **config)
        self.device = builder.AddSystem(UdpHapticDevice(self.config))
        self.source = builder.AddSystem(ConstantVectorSource(np.asarray(force, float)))
        builder.Connect(self.source.get_output_port(), self.device.get_force_input_port())
        self.logger = LogVectorOutput(self.device.get_stylus_output_port(), builder, PERIOD)
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        self.simulator.Initialize()
        self.root = self.simulator.get_mutable_context()
        self.context = self.device.GetMyContextFromRoot(self.root)
        self.ticks = 0  # server ticks done; the next is at ticks * PERIOD

    def client(self, **kwargs) -> StylusClient:
        return StylusClient(*self.device.address(), **kwargs)

    def settle(self):
        """Waits (up to 1 s) until a datagram sent on loopback can be read by the server."""
        select.select([self.device.fileno()], [], [], 1.0)

    def tick(self, n: int = 1):
        """Runs the next n server ticks; stops half a period after the last."""
        self.ticks += n
        self.simulator.AdvanceTo((self.ticks - 0.5) * PERIOD)

    def set_force(self, force):
        self.source.get_mutable_source_value(
            self.source.GetMyMutableContextFromRoot(self.root)).set_value(force)

    def stylus(self) -> np.ndarray:
        return self.device.get_stylus_output_port().Eval(self.context).copy()

    def link_ok(self) -> float:
        return self.device.get_link_ok_output_port().Eval(self.context)[0]

    def stats(self) -> dict[str, int]:
        return self.device.stats(self.context)


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.device.close()


def increments(after: dict, before: dict) -> dict:
    return {k: after[k] - before[k] for k in after if after[k] != before[k]}


def test_packets_round_trip_with_the_documented_sizes():
    # docs/udp_protocol.md: 4 + 2 + 2 + 4 + 8 + 3*8 + 4*8 + 4 and 4 + 2 + 2 + 4 + 8 + 3*8 + 4.
    assert STYLUS_SIZE == 80 and FORCE_SIZE == 48
    q = np.array([0.5, 0.5, -0.5, 0.5])
    data = pack_stylus(2**32 - 1, 12.5, [0.01, -0.02, 0.03], q, 0b11)
    assert len(data) == STYLUS_SIZE and data[:4] == b"CSTY"
    packet = unpack_stylus(data)
    assert packet.seq == 2**32 - 1 and packet.client_time == 12.5 and packet.buttons == 3
    assert_array_equal(packet.position, [0.01, -0.02, 0.03])
    assert_array_equal(packet.quaternion, q)  # already unit: unchanged
    reply = pack_force(7, 0.25, [1.0, -2.0, 3.0], STATUS_LINK_OK | STATUS_SATURATED)
    assert len(reply) == FORCE_SIZE and reply[:4] == b"CFRC"
    r = unpack_force(reply)
    assert (r.seq, r.sim_time, r.status) == (7, 0.25, 3)
    assert_array_equal(r.force, [1.0, -2.0, 3.0])
    # Little-endian on the wire, whatever the host: version 1 is b"\x01\x00".
    assert data[4:6] == b"\x01\x00" and data[8:12] == b"\xff\xff\xff\xff"
    with pytest.raises(ValueError, match="truncated"):
        unpack_force(reply[:-1])
    # A quaternion within 1e-3 of unit norm is accepted and normalised.
    near = unpack_stylus(pack_stylus(1, 0.0, [0, 0, 0], [1.0005, 0, 0, 0]))
    assert_allclose(near.quaternion, [1, 0, 0, 0], rtol=0, atol=1e-15)


def test_sequence_order_is_serial_number_arithmetic():
    assert sequence_is_newer(6, 5) and not sequence_is_newer(5, 5)
    assert not sequence_is_newer(4, 5)
    assert sequence_is_newer(0, 2**32 - 1) and sequence_is_newer(3, 2**32 - 2)
    assert not sequence_is_newer(2**32 - 1, 0)
    assert sequence_is_newer(5 + 2**31 - 1, 5) and not sequence_is_newer(5 + 2**31, 5)


def test_saturate_force():
    f, saturated, invalid = saturate_force([3.0, 4.0, 0.0], 3.3)
    assert saturated and not invalid
    assert_allclose(f, [3.3 * 0.6, 3.3 * 0.8, 0.0], rtol=1e-15)  # same direction, |f| = 3.3
    f, saturated, invalid = saturate_force([1.0, np.nan, 0.0], 3.3)
    assert invalid and not saturated
    assert_array_equal(f, np.zeros(3))
    f, saturated, invalid = saturate_force([0.0, 3.3, 0.0], 3.3)  # at the limit: untouched
    assert not saturated and not invalid and f[1] == 3.3


@pytest.mark.parametrize("field, value", [("port", 70000), ("timeout", 0.0),
                                          ("period", -1.0), ("force_limit", math.nan),
                                          ("max_packets_per_tick", 0), ("host", "")])
def test_config_is_checked(field, value):
    with pytest.raises(ValueError, match=field):
        UdpHapticDevice(UdpBridgeConfig(**{field: value}))


def test_recorded_trajectory_is_the_generated_one(tmp_path):
    regenerated = tmp_path / "trajectory.csv"
    udp_client.save_trajectory(regenerated, lissajous_trajectory())
    assert regenerated.read_text() == TRAJECTORY.read_text()
    assert TRAJECTORY.stat().st_size < 300_000
    rows = load_trajectory(TRAJECTORY)
    assert rows.shape == (3001, 9)
    assert np.all(np.abs(np.linalg.norm(rows[:, 4:8], axis=1) - 1.0) < 1e-5)


def test_replayed_trajectory_drives_the_simulation(bench):
    """Client and simulator in lockstep: one packet per server tick, every packet used."""
    rows = load_trajectory(TRAJECTORY)
    replies = []
    with bench.client() as client:
        for i, row in enumerate(rows):
            seq = client.send(row[1:4], row[4:8], int(row[8]), client_time=row[0])
            assert seq == i + 1
            bench.settle()
            bench.tick()
            replies.extend(client.receive(timeout=1.0))
    stats = bench.stats()
    assert stats["accepted"] == len(rows) == 3001
    assert sum(stats.values()) == stats["accepted"]  # nothing rejected, dropped or clipped

    # Every accepted packet is in the log, in order, used at its own tick.
    log = bench.device.received_log()
    assert_array_equal(log[:, 0], np.arange(1, len(rows) + 1))
    assert_array_equal(log[:, 1], rows[:, 0])
    assert_allclose(log[:, 2], np.arange(len(rows)) * PERIOD, atol=1e-9)

    # The logger samples at t_j before that tick's update: it shows the packet used at the
    # tick before (the last logged sim time < t_j).
    samples = bench.logger.FindLog(bench.root)
    times, data = samples.sample_times(), samples.data().T
    used = np.searchsorted(log[:, 2], times - 0.5 * PERIOD) - 1
    shown = used >= 0
    # All but the last packet, used at the final tick: the next sample would show it.
    assert shown.sum() == len(rows) - 1
    assert_array_equal(bench.stylus()[:3], rows[-1, 1:4])
    sent = rows[(log[used[shown], 0] - 1).astype(int)]
    assert_array_equal(data[shown, 0:3], sent[:, 1:4])  # positions bit for bit
    q = sent[:, 4:8] / np.linalg.norm(sent[:, 4:8], axis=1, keepdims=True)
    assert_allclose(data[shown, 3:7], q, rtol=0, atol=1e-15)
    assert_array_equal(data[shown, 7], sent[:, 8].astype(int) & 1)
    assert_array_equal(data[shown, 8], (sent[:, 8].astype(int) >> 1) & 1)
    assert_array_equal(data[~shown], [[0, 0, 0, 1, 0, 0, 0, 0, 0]])

    # One reply per tick, answering the packet of that tick, with the source's force.
    assert [r.seq for r in replies] == list(range(1, len(rows) + 1))
    assert_allclose([r.sim_time for r in replies], log[:, 2], atol=0)
    assert all(r.status == STATUS_LINK_OK for r in replies)
    assert_array_equal(np.array([r.force for r in replies]), np.tile(FORCE, (len(rows), 1)))


@pytest.mark.slow
def test_cli_client_against_a_realtime_simulation(bench, tmp_path):
    """`python -m capsule_drake.teleop.udp_client` in its own process at the recorded
    timestamps, the simulation paced to the wall clock in small steps."""
    rows = load_trajectory(TRAJECTORY)
    replies_csv = tmp_path / "replies.csv"
    command = [sys.executable, "-m", "capsule_drake.teleop.udp_client", str(TRAJECTORY),
               "--host", "127.0.0.1", "--port", str(bench.device.port()),
               "--log", str(replies_csv), "--linger", "0.1"]
    start = time.monotonic()
    client = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    try:
        while client.poll() is None and time.monotonic() - start < 9.0:
            # One tick per period of wall-clock time, as a simulator at realtime rate 1.
            delay = start + bench.ticks * PERIOD - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            bench.tick()
    finally:
        if client.poll() is None:
            client.kill()
    _, err = client.communicate()
    assert client.returncode == 0, err
    assert "sent 3001 stylus packets" in err

    stats = bench.stats()
    print("replay in real time:", {k: v for k, v in stats.items() if v})
    # The client's clock and the server's ticks drift: a tick may see two packets (one
    # superseded) or none. Every packet sent is accounted for; none is rejected.
    assert stats["accepted"] + stats["superseded"] + stats["kernel_dropped"] == 3001
    assert stats["accepted"] > 300  # used, not only counted (~2900 unloaded, ~1400 loaded)
    assert all(stats[name] == 0 for name in STATS_NAMES[2:11])
    log = bench.device.received_log()
    assert len(log) == stats["accepted"] and np.all(np.diff(log[:, 0]) > 0)

    samples = bench.logger.FindLog(bench.root)
    times, data = samples.sample_times(), samples.data().T
    used = np.searchsorted(log[:, 2], times - 0.5 * PERIOD) - 1
    shown = used >= 0
    sent = rows[(log[used[shown], 0] - 1).astype(int)]
    assert_array_equal(data[shown, 0:3], sent[:, 1:4])
    assert_array_equal(data[shown, 7], sent[:, 8].astype(int) & 1)

    replies = np.loadtxt(replies_csv, delimiter=",", skiprows=1, ndmin=2)
    assert len(replies) > 2000
    seqs = replies[:, 1]
    assert np.all(np.diff(seqs) >= 0) and set(seqs) <= set(log[:, 0])
    assert np.all(np.diff(replies[:, 2]) > 0)  # one reply per tick
    # The client lingers 0.1 s after its last packet, as long as the link timeout, so the
    # server may declare the link lost while the client still listens (a loaded machine can
    # also stall the client mid-run): those replies say so and carry zero force (the safety
    # rule); all others carry the source's force.
    link_ok = (replies[:, 6].astype(int) & STATUS_LINK_OK) != 0
    assert link_ok.sum() > 2000
    assert stats["link_losses"] >= 1 or link_ok.all()
    assert_allclose(replies[link_ok, 3:6], np.tile(FORCE, (link_ok.sum(), 1)), rtol=1e-9)
    assert_array_equal(replies[~link_ok, 3:6], 0.0)


def test_bad_packets_are_counted_and_never_stop_the_simulation(bench):
    client = bench.client(first_seq=100)
    seq = 100
    used = []  # seqs of the valid packets, each must be used

    def good(position):
        nonlocal seq
        client.send_raw(pack_stylus(seq, 0.01 * seq, position, [1, 0, 0, 0], 1))
        bench.settle()
        bench.tick()
        assert_array_equal(bench.stylus()[:3], position)
        assert bench.link_ok() == 1.0
        used.append(seq)
        seq += 1

    def stylus(position=(0.0, 0.0, 0.0), quaternion=(1.0, 0.0, 0.0, 0.0), client_time=0.0,
               **header):  # a packet with the next seq, one thing wrong
        return pack_stylus(seq, client_time, position, quaternion, 0, **header)

    cases = [
        ("bad_magic", lambda: stylus(magic=b"XSTY")),
        ("bad_magic", lambda: pack_force(seq, 0.0, [0, 0, 0], 0) + bytes(32)),  # padded reply
        ("bad_version", lambda: stylus(version=2)),
        ("bad_version", lambda: stylus(version=0)),
        ("truncated", lambda: b""),
        ("truncated", lambda: stylus()[:-1]),
        ("truncated", lambda: pack_force(seq, 0.0, [0, 0, 0], 0)),
        ("oversized", lambda: stylus() + b"\x00"),
        ("oversized", lambda: stylus() + bytes(1400)),
        ("oversized", lambda: stylus() * 100),  # 8000 bytes
        ("non_finite", lambda: stylus(position=[math.nan, 0.0, 0.0])),
        ("non_finite", lambda: stylus(quaternion=[math.inf, 0.0, 0.0, 0.0])),
        ("non_finite", lambda: stylus(client_time=-math.inf)),
        ("position_out_of_range", lambda: stylus(position=[1.2, 0.0, 0.0])),
        ("position_out_of_range", lambda: stylus(position=[0.6, 0.6, 0.6])),  # 1.04 m
        ("quaternion_not_unit", lambda: stylus(quaternion=[1.01, 0.0, 0.0, 0.0])),
        ("quaternion_not_unit", lambda: stylus(quaternion=[0.0, 0.0, 0.0, 0.0])),
        ("duplicate", lambda: pack_stylus(seq - 1, 0.0, [0.5, 0, 0], [1, 0, 0, 0])),
        ("out_of_order", lambda: pack_stylus(seq - 5, 0.0, [0.5, 0, 0], [1, 0, 0, 0])),
    ]
    good([0.01, 0.02, 0.03])
    expected = dict.fromkeys(STATS_NAMES, 0)
    for n, (reason, make) in enumerate(cases):
        held = bench.stylus()
        before = bench.stats()
        assert client.send_raw(make())
        bench.settle()
        bench.tick()  # the simulation goes on
        assert increments(bench.stats(), before) == {reason: 1}, reason
        assert_array_equal(bench.stylus(), held)  # the bad packet changed nothing
        expected[reason] += 1
        good([0.001 * n, -0.002, 0.003])  # and the next valid packet is used

    # A quaternion 5e-4 off unit norm is accepted, normalised.
    client.send_raw(stylus(quaternion=[0.0, 0.0, 1.0005, 0.0]))
    used.append(seq)
    seq += 1
    bench.settle()
    bench.tick()
    assert_allclose(bench.stylus()[3:7], [0, 0, 1, 0], atol=1e-15)

    expected["accepted"] = len(used)
    assert bench.stats() == expected
    assert expected["accepted"] == 21 and sum(expected.values()) == 21 + 19
    assert_array_equal(bench.device.received_log()[:, 0], used)  # none lost
    client.close()


def test_sequence_wraps_around_in_the_server(bench):
    with bench.client(first_seq=2**32 - 2) as client:
        for k, expected_seq in enumerate((2**32 - 2, 2**32 - 1, 0, 1)):
            assert client.send([0.0, 0.0, 0.001 * k]) == expected_seq
            bench.settle()
            bench.tick()
        client.send_raw(pack_stylus(2**32 - 1, 0.0, [0, 0, 0], [1, 0, 0, 0]))  # from before
        bench.settle()
        bench.tick()
    stats = bench.stats()
    assert stats["accepted"] == 4 and stats["out_of_order"] == 1
    assert_array_equal(bench.device.received_log()[:, 0], [2**32 - 2, 2**32 - 1, 0, 1])


def test_a_flood_is_absorbed(bench):
    """10,000 valid packets in one burst between two ticks: the server reads what the
    socket buffer held, uses the newest and counts the rest as superseded; what the OS
    dropped on the full buffer is counted (Linux) when the next datagram arrives."""
    with bench.client() as client:
        client.send([0.0, 0.0, 0.0])
        bench.settle()
        bench.tick()
        before = bench.stats()
        first = client.seq
        for i in range(10_000):
            client.send([0.0, 0.0, 1e-5 * i])
        assert client.errors == 0
        bench.settle()
        t0 = time.monotonic()
        bench.tick()
        drain_time = time.monotonic() - t0
        while True:  # a buffer larger than max_packets_per_tick takes more ticks
            previous = bench.stats()
            bench.tick()
            if bench.stats()["superseded"] == previous["superseded"]:
                break
        assert bench.link_ok() == 1.0
        after_flood = bench.stats()
        client.send([0.01, 0.01, 0.01])  # the first packet after: used, carries drop count
        bench.settle()
        bench.tick()
        assert_array_equal(bench.stylus()[:3], [0.01, 0.01, 0.01])
    change = increments(bench.stats(), before)
    flood_accepted = after_flood["accepted"] - before["accepted"]
    received = flood_accepted + change["superseded"]
    dropped = change.get("kernel_dropped", 0)
    print(f"flood: accepted {flood_accepted}, superseded {change['superseded']}, dropped by "
          f"the kernel {dropped}, first drain {1e3 * drain_time:.1f} ms")
    assert received + dropped == 10_000
    assert set(change) <= {"accepted", "superseded", "kernel_dropped"}  # no rejection
    assert change["accepted"] == flood_accepted + 1
    log = bench.device.received_log()
    assert len(log) == bench.stats()["accepted"] and np.all(np.diff(log[:, 0]) > 0)
    # The OS drops the tail of the burst: the newest packet read is number `received`.
    assert log[-2, 0] == first + received - 1
    assert drain_time < 1.0


def test_random_garbage_is_counted(bench):
    """Random datagrams (random sizes, and the right header with a random payload): each one
    counted exactly once, under some reason, and the simulation runs on."""
    rng = np.random.default_rng(7)
    header = pack_stylus(0, 0.0, [0, 0, 0], [1, 0, 0, 0])[:8]
    sent = 0
    with bench.client() as client:
        for _ in range(20):
            for _ in range(50):
                if rng.random() < 0.5:
                    data = rng.bytes(int(rng.integers(0, 200)))
                else:
                    data = header + rng.bytes(STYLUS_SIZE - 8)
                sent += client.send_raw(data)
            bench.settle()
            bench.tick()
    stats = bench.stats()
    counted = sum(stats[name] for name in STATS_NAMES[:11])
    assert counted + stats["kernel_dropped"] == sent == 1000
    assert stats["kernel_dropped"] == 0
    assert len(bench.device.received_log()) == stats["accepted"]
    for data in (rng.bytes(80) for _ in range(1000)):  # the decoder never raises
        decode_stylus(data)


def test_link_loss_holds_the_pose_and_zeroes_the_force(bench):
    client = bench.client()
    pose = ([0.02, -0.01, 0.005], [0.0, 1.0, 0.0, 0.0], 3)
    for _ in range(20):
        client.send(*pose)
        bench.settle()
        bench.tick()
    client.receive()
    last_time = bench.device.received_log()[-1, 2]
    held = bench.stylus()
    assert_array_equal(held, [0.02, -0.01, 0.005, 0, 1, 0, 0, 1, 1])

    # Silence: still linked just before the timeout...
    bench.tick(int(round((last_time + 0.1) / PERIOD)) - bench.ticks)
    assert bench.link_ok() == 1.0
    replies = client.receive(timeout=1.0)
    assert replies[-1].status == STATUS_LINK_OK
    assert_array_equal(replies[-1].force, FORCE)
    # ...lost at the tick `timeout` after the last packet (allowing one tick of rounding).
    bench.tick(2)
    assert bench.link_ok() == 0.0
    assert_array_equal(bench.stylus(), held)
    replies = client.receive(timeout=1.0)
    assert replies[-1].status == 0 and replies[-1].seq == 20
    assert_array_equal(replies[-1].force, np.zeros(3))
    bench.tick(200)  # stays lost, keeps holding, replies zero
    assert bench.link_ok() == 0.0 and bench.stats()["link_losses"] == 1
    assert_array_equal(bench.stylus(), held)
    replies = client.receive(timeout=1.0)
    assert len(replies) == 200 and all(not r.force.any() and r.status == 0 for r in replies)
    client.close()

    # A restarted client (new port, numbering from 1 again) is accepted after the loss.
    with bench.client(first_seq=1) as restarted:
        restarted.send([0.0, 0.03, 0.0])
        bench.settle()
        bench.tick()
        assert bench.link_ok() == 1.0
        assert_array_equal(bench.stylus()[:3], [0.0, 0.03, 0.0])
        reply = restarted.receive(timeout=1.0)[-1]
        assert reply.seq == 1 and reply.status == STATUS_LINK_OK
        assert_array_equal(reply.force, FORCE)
    stats = bench.stats()
    assert stats["accepted"] == 21 and stats["link_losses"] == 1


def test_force_saturation_and_non_finite_force(bench):
    with bench.client() as client:
        def reply_for(force):
            bench.set_force(force)
            client.send([0.0, 0.0, 0.0])
            bench.settle()
            bench.tick()
            return client.receive(timeout=1.0)[-1]

        r = reply_for([3.0, 3.0, 0.0])  # 4.24 N: clipped to 3.3 N, same direction
        assert r.status == STATUS_LINK_OK | STATUS_SATURATED
        assert_allclose(r.force, [3.3 / math.sqrt(2)] * 2 + [0.0], rtol=1e-15)
        r = reply_for([np.nan, 0.1, 0.0])
        assert r.status == STATUS_LINK_OK | STATUS_FORCE_INVALID
        assert_array_equal(r.force, np.zeros(3))
        r = reply_for([0.0, -np.inf, 0.0])
        assert r.status == STATUS_LINK_OK | STATUS_FORCE_INVALID
        assert_array_equal(r.force, np.zeros(3))
        r = reply_for([0.0, 0.0, -3.3])  # at the limit: sent as is
        assert r.status == STATUS_LINK_OK
        assert_array_equal(r.force, [0.0, 0.0, -3.3])
    stats = bench.stats()
    assert stats["force_saturated"] == 1 and stats["force_non_finite"] == 2
    assert stats["accepted"] == 4


def test_unconnected_force_input_sends_zero():
    with UdpHapticDevice(UdpBridgeConfig(period=PERIOD)) as device:
        context = device.CreateDefaultContext()
        simulator = Simulator(device, context)
        with StylusClient(*device.address()) as client:
            client.send([0.0, 0.0, 0.0])
            select.select([device.fileno()], [], [], 1.0)
            simulator.AdvanceTo(0.5 * PERIOD)
            reply = client.receive(timeout=1.0)[-1]
        assert reply.status == STATUS_LINK_OK and not reply.force.any()


def test_socket_is_closed_by_close_and_by_garbage_collection():
    device = UdpHapticDevice()
    address = device.address()
    device.close()
    device.close()  # idempotent
    assert device.fileno() == -1
    simulator = Simulator(device)
    simulator.AdvanceTo(0.01)  # ticks without a socket run, do nothing
    _rebind(address)

    def build_and_drop():
        builder = DiagramBuilder()
        builder.AddSystem(UdpHapticDevice())
        diagram = builder.Build()
        return diagram.GetSystems()[0].address()

    address = build_and_drop()
    gc.collect()
    _rebind(address)  # the port is free again: the socket was closed


def _rebind(address):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(address)


if __name__ == "__main__":
    udp_client.save_trajectory(TRAJECTORY, lissajous_trajectory())
    print(f"wrote {TRAJECTORY} ({TRAJECTORY.stat().st_size} bytes)")
