"""UDP bridge to a real haptic device: the simulator is the server, the device a client.

A device-side client (Phantom Omni / Geomagic Touch class: 6-DoF pose, 2 buttons, 3-DoF
force, 1 kHz servo loop, 3.3 N peak) streams "stylus" datagrams; the simulator answers each
of its ticks with a "force" datagram. The wire format (little-endian, fixed sizes) and the
acceptance rules are specified in docs/udp_protocol.md; this module is their implementation:
the codec (pure functions, no socket) and ``UdpHapticDevice``, the LeafSystem that owns the
server socket.
"""

import array
import concurrent.futures
import copy
import dataclasses
import logging
import math
import socket
import struct
import sys
import weakref
from typing import NamedTuple

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from capsule_drake.guidance.terms import saturate_checked as saturate_force
from capsule_drake.schema import need_range

log = logging.getLogger(__name__)

STYLUS_MAGIC = b"CSTY"
FORCE_MAGIC = b"CFRC"
PROTOCOL_VERSION = 1
# magic, version, flags, sequence, client time, position (3), quaternion wxyz (4), buttons.
_STYLUS = struct.Struct("<4sHHId3d4dI")
# magic, version, flags, answered sequence, server sim time, force (3), status.
_FORCE = struct.Struct("<4sHHId3dI")
STYLUS_SIZE = _STYLUS.size  # 80 bytes
FORCE_SIZE = _FORCE.size  # 48 bytes

# Stylus `buttons` bits (the others are ignored).
BUTTON_CLUTCH = 1 << 0
BUTTON_MODE = 1 << 1
# Force `status` bits (the others are 0).
STATUS_LINK_OK = 1 << 0
STATUS_SATURATED = 1 << 1
STATUS_FORCE_INVALID = 1 << 2

# Acceptance limits of a stylus packet.
MAX_POSITION_NORM = 1.0  # m, from the workspace centre
QUATERNION_NORM_TOLERANCE = 1e-3  # | |q| - 1 | above this: rejected; below: normalised

_SEQ_MODULUS = 1 << 32

# Order of the `stats` output. The rejection reasons (truncated ... out_of_order) are the
# first check a stylus packet fails, in this order.
REJECTION_REASONS = ("truncated", "oversized", "bad_magic", "bad_version", "non_finite",
                     "position_out_of_range", "quaternion_not_unit", "duplicate",
                     "out_of_order")
STATS_NAMES = (("accepted", "superseded") + REJECTION_REASONS
               + ("force_non_finite", "force_saturated", "link_losses", "kernel_dropped",
                  "socket_errors", "log_full"))
_STAT = {name: i for i, name in enumerate(STATS_NAMES)}

# Linux's SO_RXQ_OVFL (asm-generic/socket.h; not exported by Python's socket module): each
# received datagram carries the socket's count of datagrams dropped on a full receive buffer.
_SO_RXQ_OVFL = 40


class StylusPacket(NamedTuple):
    """A decoded client -> server datagram. position: (3,) m in the device frame D;
    quaternion: (4,) w, x, y, z (normalised by `decode_stylus`)."""
    seq: int
    client_time: float
    position: np.ndarray
    quaternion: np.ndarray
    buttons: int
    flags: int = 0


class ForcePacket(NamedTuple):
    """A decoded server -> client datagram. force: (3,) N in the device frame D."""
    seq: int
    sim_time: float
    force: np.ndarray
    status: int
    flags: int = 0


def pack_stylus(seq: int, client_time: float, position, quaternion, buttons: int = 0, *,
                flags: int = 0, magic: bytes = STYLUS_MAGIC,
                version: int = PROTOCOL_VERSION) -> bytes:
    """Encodes a stylus datagram (STYLUS_SIZE bytes). Values are not checked beyond what the
    field types hold (a NaN position packs), so tests can build bad packets; `magic` and
    `version` are there for the same reason."""
    p = np.asarray(position, dtype=float).reshape(3)
    q = np.asarray(quaternion, dtype=float).reshape(4)
    return _STYLUS.pack(magic, version, flags, seq, client_time, *p, *q, buttons)


def decode_stylus(data: bytes) -> tuple[StylusPacket | None, str | None]:
    """Decodes and checks a stylus datagram without raising: (packet, None) or (None, reason)
    with reason one of REJECTION_REASONS except the sequence ones (the caller's)."""
    if len(data) < STYLUS_SIZE:
        return None, "truncated"
    if len(data) > STYLUS_SIZE:
        return None, "oversized"
    fields = _STYLUS.unpack(data)
    magic, version, flags, seq, client_time = fields[:5]
    if magic != STYLUS_MAGIC:
        return None, "bad_magic"
    if version != PROTOCOL_VERSION:
        return None, "bad_version"
    if not all(math.isfinite(v) for v in fields[4:12]):
        return None, "non_finite"
    if math.hypot(*fields[5:8]) > MAX_POSITION_NORM:  # hypot: no overflow on 1e300
        return None, "position_out_of_range"
    norm = math.hypot(*fields[8:12])
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        return None, "quaternion_not_unit"
    return StylusPacket(seq, client_time, np.array(fields[5:8]), np.array(fields[8:12]) / norm,
                        fields[12], flags), None


def unpack_stylus(data: bytes) -> StylusPacket:
    """`decode_stylus`, raising ValueError with the rejection reason."""
    packet, reason = decode_stylus(data)
    if packet is None:
        raise ValueError(f"stylus packet rejected: {reason}")
    return packet


def pack_force(seq: int, sim_time: float, force, status: int, *, flags: int = 0) -> bytes:
    """Encodes a force datagram (FORCE_SIZE bytes)."""
    f = np.asarray(force, dtype=float).reshape(3)
    return _FORCE.pack(FORCE_MAGIC, PROTOCOL_VERSION, flags, seq, sim_time, *f, status)


def decode_force(data: bytes) -> tuple[ForcePacket | None, str | None]:
    """Decodes and checks a force datagram without raising: (packet, None) or (None, reason),
    reason in truncated, oversized, bad_magic, bad_version, non_finite."""
    if len(data) < FORCE_SIZE:
        return None, "truncated"
    if len(data) > FORCE_SIZE:
        return None, "oversized"
    magic, version, flags, seq, sim_time, fx, fy, fz, status = _FORCE.unpack(data)
    if magic != FORCE_MAGIC:
        return None, "bad_magic"
    if version != PROTOCOL_VERSION:
        return None, "bad_version"
    if not all(math.isfinite(v) for v in (sim_time, fx, fy, fz)):
        return None, "non_finite"
    return ForcePacket(seq, sim_time, np.array([fx, fy, fz]), status, flags), None


def unpack_force(data: bytes) -> ForcePacket:
    """`decode_force`, raising ValueError with the rejection reason."""
    packet, reason = decode_force(data)
    if packet is None:
        raise ValueError(f"force packet rejected: {reason}")
    return packet


def sequence_is_newer(seq: int, reference: int) -> bool:
    """Serial-number order of uint32 sequence numbers (RFC 1982): `seq` is newer when it is
    1 to 2**31 - 1 steps after `reference`, modulo 2**32 (so 0 follows 2**32 - 1)."""
    return 0 < (int(seq) - int(reference)) % _SEQ_MODULUS < _SEQ_MODULUS // 2


@dataclasses.dataclass
class UdpBridgeConfig:
    """The UDP server of the haptic bridge; YAML-loadable, all fields default."""

    # Address to bind. The loopback default keeps the simulator private to this machine. Any
    # other address ("0.0.0.0", a LAN address) exposes it: the protocol has no
    # authentication, so whoever reaches the port steers the stylus input and gets replies.
    host: str = "127.0.0.1"
    # UDP port; 0 = an ephemeral port chosen by the OS (read it back with `port()`).
    port: int = 0
    # Link timeout (s of simulation time): without a valid packet for this long the link is
    # lost (link_ok = 0, stylus held, zero force sent).
    timeout: float = 0.1
    # Server tick (s): socket polled, force sent. 1 ms = the device's 1 kHz servo loop.
    period: float = 0.001
    # Norm limit of the force sent (N): the Phantom Omni / Geomagic Touch peak force.
    force_limit: float = 3.3
    # At most this many datagrams read per tick, so a flood cannot stall a tick for long
    # (about 5 us each); the rest wait in the socket buffer for the next tick.
    max_packets_per_tick: int = 4096
    # At most this many entries in `received_log()` (24 bytes each; 3.6e6 = one hour at
    # 1 kHz); accepted packets beyond it are counted in stats `log_full`, not logged.
    received_log_limit: int = 3_600_000


def check_udp_bridge_config(config: UdpBridgeConfig) -> None:
    """Raises ValueError naming the first impossible field. (Whether the host resolves and
    the port can be bound is `check_udp_address`'s: it asks the network.)"""
    if not isinstance(config.host, str) or not config.host:
        raise ValueError(f"udp bridge host {config.host!r} must be a non-empty string")
    if len(config.host) > 253 or any(c.isspace() or not c.isprintable() for c in config.host):
        raise ValueError(f"udp bridge host {config.host[:60]!r} must be a host name or address "
                         "(at most 253 characters, no spaces)")
    need_range(config.port, "udp.port", "[0, 65535]", "", "0: any free port")
    need_range(config.timeout, "udp.timeout", "> 0", "s")
    need_range(config.period, "udp.period", ">= 0.0001", "s", "the device sends at 1 kHz")
    need_range(config.force_limit, "udp.force_limit", "> 0", "N")
    need_range(config.max_packets_per_tick, "udp.max_packets_per_tick", "[1, 65536]")
    need_range(config.received_log_limit, "udp.received_log_limit",
               f"[0, {MAX_RECEIVED_LOG}]", "",
               f"24 bytes each: {MAX_RECEIVED_LOG * 24 / 1e9:.2g} GB, 10 hours at 1 kHz")


MAX_RECEIVED_LOG = 36_000_000
"""Most entries of `received_log()` (24 bytes each): 10 hours of packets at 1 kHz."""
RESOLVE_TIMEOUT = 5.0
"""How long (s) `check_udp_address` waits for the host's name to resolve."""


def check_udp_address(config: UdpBridgeConfig) -> None:
    """Raises ValueError (one line) unless the bridge's host resolves, within
    RESOLVE_TIMEOUT, and a socket can be bound to (host, port) as the bridge will bind it
    (the socket is closed at once)."""
    family = socket.AF_INET6 if ":" in config.host else socket.AF_INET
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    try:
        pool.submit(socket.getaddrinfo, config.host, config.port, family,
                    socket.SOCK_DGRAM).result(timeout=RESOLVE_TIMEOUT)
    except concurrent.futures.TimeoutError:
        raise ValueError(f"udp bridge host {config.host!r} did not resolve within "
                         f"{RESOLVE_TIMEOUT:g} s") from None
    except (OSError, UnicodeError) as e:
        reason = getattr(e, "strerror", None) or str(e) or type(e).__name__
        raise ValueError(f"udp bridge host {config.host!r} does not resolve ({reason})") from None
    finally:
        pool.shutdown(wait=False)
    try:
        _open_socket(config.host, config.port).close()
    except OSError as e:
        raise ValueError(f"udp bridge cannot bind {config.host}:{config.port} "
                         f"({e.strerror or e})") from None


# The stylus output before the first packet: at the workspace centre, identity, no button.
_STYLUS_INITIAL = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]


class UdpHapticDevice(LeafSystem):
    """A haptic device on the network: the stylus a UDP client sends, the force sent back.

    Every ``config.period`` s (first at t = 0) the system drains its non-blocking socket,
    checks each datagram (docs/udp_protocol.md), keeps the newest valid one (the other valid
    ones of the tick count as superseded) and holds its stylus; then it sends ``force_D``,
    saturated, to the address of the last accepted packet. The stylus held, the last
    sequence number, the counters and the time of the last valid packet are discrete state,
    so the outputs are pure functions of the context. A bad datagram is counted and dropped;
    nothing from the network raises.

    Timing is simulation time: the timeout counts simulated seconds and replies carry the
    tick's simulated time. The simulation may run faster or slower than real time: faster,
    the timeout shrinks in wall-clock terms (at 10x, 0.1 s is 10 ms) and the link drops
    between the device's packets; slower, the device gets fewer, staler forces than its
    1 kHz loop wants. With a real device, run the simulator at
    ``set_target_realtime_rate(1.0)`` and make sure it keeps up.

    .. pydrake_system::

        name: UdpHapticDevice
        input_ports:
        - force_D
        output_ports:
        - stylus
        - link_ok
        - stats

    - ``force_D`` (3, N): force on the stylus in the device frame D (x right, y up, z toward
      the operator). Evaluated at each tick, i.e. from the outputs held before that tick's
      packets (a one-period delay, as in the device's own servo loop). Sent saturated by norm
      to ``force_limit``; NaN/inf replaced by zero (counted); zero while the link is lost;
      unconnected = zero.
    - ``stylus`` (9): position (m, D, from the workspace centre), quaternion of R_DS with S
      the stylus frame (w, x, y, z, unit), clutch (1.0/0.0, button bit 0), mode (1.0/0.0,
      button bit 1). Held while the link is lost (buttons included: gate on ``link_ok``);
      [0, 0, 0, 1, 0, 0, 0, 0, 0] before the first packet.
    - ``link_ok`` (1): 1.0 from the first valid packet until ``timeout`` s without one.
    - ``stats`` (17): counters in the order of ``STATS_NAMES``: accepted, superseded, one
      per rejection reason (truncated, oversized, bad_magic, bad_version, non_finite,
      position_out_of_range, quaternion_not_unit, duplicate, out_of_order),
      force_non_finite (ticks whose force_D was not finite), force_saturated (replies
      clipped), link_losses, kernel_dropped (datagrams the OS dropped on a full receive
      buffer, as Linux reports them with the next datagram received; 0 elsewhere),
      socket_errors, log_full. ``stats(context)`` gives them as a dict.

    When the link is lost the sequence reference is forgotten, so a restarted client whose
    numbering starts again is accepted. Every accepted packet's (seq, client time, sim time
    of the tick that used it) is appended to ``received_log()``; that log and the socket
    live in the system, not the context: use one system with one simulator at a time.
    Close the socket with ``close()`` (or ``with UdpHapticDevice(...) as device:``); it is
    also closed when the system is garbage collected.

    Args:
        config: a ``UdpBridgeConfig`` (checked and copied). The socket is bound here.
    """

    def __init__(self, config: UdpBridgeConfig | None = None):
        super().__init__()
        self._config = copy.deepcopy(config) if config is not None else UdpBridgeConfig()
        check_udp_bridge_config(self._config)
        c = self._config
        self._socket = _open_socket(c.host, c.port)
        self._finalizer = weakref.finalize(self, self._socket.close)
        self._address = self._socket.getsockname()[:2]
        self._report_drops = False
        if sys.platform.startswith("linux") and hasattr(self._socket, "recvmsg_into"):
            try:
                self._socket.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
                self._report_drops = True
            except OSError:
                pass
        self._ancillary_size = socket.CMSG_SPACE(4) if self._report_drops else 0
        self._buffer = bytearray(65536)  # the largest UDP payload
        self._log = array.array("d")

        self._force_port = self.DeclareVectorInputPort("force_D", 3)
        self._stylus = self.DeclareDiscreteState(BasicVector(_STYLUS_INITIAL))
        self._link_ok = self.DeclareDiscreteState(1)
        # [sequence reference valid (0/1), last accepted seq, sim time of the last accepted]
        self._link = self.DeclareDiscreteState(BasicVector([0.0, 0.0, -math.inf]))
        self._stats = self.DeclareDiscreteState(len(STATS_NAMES))
        # The last accepted packet's source address; () before the first.
        self._reply_to = self.DeclareAbstractState(AbstractValue.Make(()))
        self._stylus_port = self.DeclareStateOutputPort("stylus", self._stylus)
        self._link_ok_port = self.DeclareStateOutputPort("link_ok", self._link_ok)
        self._stats_port = self.DeclareStateOutputPort("stats", self._stats)
        self.DeclarePeriodicUnrestrictedUpdateEvent(c.period, 0.0, self._update)

    def config(self) -> UdpBridgeConfig:
        return copy.deepcopy(self._config)

    def address(self) -> tuple[str, int]:
        """(host, port) the socket is bound to."""
        return self._address

    def port(self) -> int:
        """The bound UDP port (the ephemeral one chosen when config.port is 0)."""
        return self._address[1]

    def fileno(self) -> int:
        """The socket's file descriptor (for select()); -1 once closed."""
        return -1 if self._socket is None else self._socket.fileno()

    def close(self) -> None:
        """Closes the socket; later ticks only run the timeout. Idempotent."""
        self._finalizer()
        self._socket = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def get_force_input_port(self):
        return self._force_port

    def get_stylus_output_port(self):
        return self._stylus_port

    def get_link_ok_output_port(self):
        return self._link_ok_port

    def get_stats_output_port(self):
        return self._stats_port

    def stats(self, context) -> dict[str, int]:
        """The `stats` output of this system's `context` as {name: count}."""
        values = self._stats_port.Eval(context)
        return {name: int(v) for name, v in zip(STATS_NAMES, values)}

    def received_log(self) -> np.ndarray:
        """(N, 3) [seq, client time (s), sim time of the tick that used it (s)], one row per
        accepted packet in order (a copy)."""
        return np.array(self._log).reshape(-1, 3)

    def _drain(self, stats: np.ndarray) -> list[tuple[bytes, tuple]]:
        """Reads up to max_packets_per_tick datagrams; (payload, source address) each."""
        datagrams = []
        if self._socket is None:
            return datagrams
        keep = STYLUS_SIZE + 1  # enough to tell an oversized datagram; the rest is not kept
        for _ in range(self._config.max_packets_per_tick):
            try:
                if self._report_drops:
                    size, ancillary, _, source = self._socket.recvmsg_into(
                        [self._buffer], self._ancillary_size)
                    for level, kind, data in ancillary:
                        if level == socket.SOL_SOCKET and kind == _SO_RXQ_OVFL:
                            dropped = struct.unpack("=I", data[:4])[0]
                            stats[_STAT["kernel_dropped"]] = max(
                                stats[_STAT["kernel_dropped"]], dropped)
                else:
                    size, source = self._socket.recvfrom_into(self._buffer)
            except BlockingIOError:
                break
            except OSError:  # e.g. ECONNREFUSED left by an ICMP error for an earlier reply
                stats[_STAT["socket_errors"]] += 1
                continue
            datagrams.append((bytes(self._buffer[:min(size, keep)]), source))
        return datagrams

    def _update(self, context, state):
        t = context.get_time()
        stats = context.get_discrete_state(self._stats).value().copy()
        has_reference, last_seq, last_time = context.get_discrete_state(self._link).value()
        link_ok = context.get_discrete_state(self._link_ok).value()[0] > 0.5
        reference = int(last_seq) if has_reference > 0.5 else None
        newest = None
        for data, source in self._drain(stats):
            packet, reason = decode_stylus(data)
            if packet is None:
                stats[_STAT[reason]] += 1
                continue
            against = newest[0].seq if newest is not None else reference
            if against is not None and not sequence_is_newer(packet.seq, against):
                stats[_STAT["duplicate" if packet.seq == against else "out_of_order"]] += 1
                continue
            if newest is not None:
                stats[_STAT["superseded"]] += 1
            newest = (packet, source)

        if newest is not None:
            packet, source = newest
            stats[_STAT["accepted"]] += 1
            if not link_ok:
                log.info("UDP haptic link up at t = %.3f s (seq %d from %s)", t, packet.seq,
                         source)
            link_ok, last_seq, last_time = True, packet.seq, t
            stylus = np.concatenate([packet.position, packet.quaternion,
                                     [1.0 if packet.buttons & BUTTON_CLUTCH else 0.0,
                                      1.0 if packet.buttons & BUTTON_MODE else 0.0]])
            state.get_mutable_discrete_state(self._stylus).set_value(stylus)
            state.get_mutable_discrete_state(self._link).set_value([1.0, last_seq, t])
            state.get_mutable_abstract_state(self._reply_to).set_value(tuple(source))
            if len(self._log) < 3 * self._config.received_log_limit:
                self._log.extend((packet.seq, packet.client_time, t))
            else:
                stats[_STAT["log_full"]] += 1
        elif link_ok and t - last_time >= self._config.timeout:
            link_ok = False
            stats[_STAT["link_losses"]] += 1
            state.get_mutable_discrete_state(self._link).set_value([0.0, last_seq, last_time])
            log.info("UDP haptic link lost at t = %.3f s (last packet at %.3f s)", t,
                     last_time)
        state.get_mutable_discrete_state(self._link_ok).set_value([1.0 if link_ok else 0.0])

        force = self._force_port.Eval(context) if self._force_port.HasValue(context) else 0.0
        force, saturated, invalid = saturate_force(np.broadcast_to(force, 3),
                                                   self._config.force_limit)
        stats[_STAT["force_non_finite"]] += invalid
        if not link_ok:
            force, saturated = np.zeros(3), False
        reply_to = context.get_abstract_state(self._reply_to).get_value()
        if newest is not None:
            reply_to = tuple(newest[1])
        if reply_to and self._socket is not None:
            stats[_STAT["force_saturated"]] += saturated
            status = ((STATUS_LINK_OK if link_ok else 0) | (STATUS_SATURATED if saturated else 0)
                      | (STATUS_FORCE_INVALID if invalid else 0))
            try:
                self._socket.sendto(pack_force(int(last_seq), t, force, status), reply_to)
            except OSError:  # BlockingIOError on a full send buffer, ECONNREFUSED, ...
                stats[_STAT["socket_errors"]] += 1
        state.get_mutable_discrete_state(self._stats).set_value(stats)
        return EventStatus.Succeeded()


def _open_socket(host: str, port: int) -> socket.socket:
    """A non-blocking UDP socket bound to (host, port), IPv4 or IPv6 by the host's form."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setblocking(False)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock
