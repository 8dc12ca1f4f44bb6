"""The run's channels live in Foxglove: a WebSocket server (foxglove-sdk) on the loopback.

Each channel the run writes (app/channels.py) is advertised with its ROS 2 type as a
`ros2msg` schema and its payload in CDR (the bytes the MCAP file holds), so Foxglove decodes
it as it decodes the MCAP file. The channels are made before the server listens (the run
declares its topics first: `declare`, then `start`), so a viewer is offered all of them in
the advertisement it gets when it connects. A channel advertised to a viewer already
connected can lose that viewer's subscription: foxglove-sdk (0.30) sends the advertisement
before it records the channel for that client, and a prompt subscription is refused as
"unknown channel" (seen here on a loaded machine, about one run in three, with the camera's
channel advertised at its first frame). A latched channel (/tf_static, the scene) is sent
again to a client that subscribes to it later. The server is an output a run may lose: a
failure is one line and the run goes on (app/channels.py).
"""

from __future__ import annotations

import threading
import time

from capsule_drake.app.outputs import OutputError
from capsule_drake.app.ros2_messages import schema_text


RESEND_AFTER = (0.1, 1.0, 3.0)
"""Seconds after a subscription at which a latched channel is sent again: the server calls
its listener before it adds the subscription, and a client too slow for the stream has its
oldest queued messages dropped (foxglove-sdk's backlog, `backlog` messages), so once is not
enough on a loaded machine."""


def _listener(live: "FoxgloveLive"):
    """A foxglove ServerListener that tells `live` of each subscription (foxglove-sdk is
    imported when a server is made: a run without one does not load it)."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_subscribe(self, client, channel) -> None:
            live.subscribed(channel.topic)

    return Listener()


class FoxgloveLive:
    """A Foxglove WebSocket server streaming the channels given to `publish`: made, told the
    run's topics (`declare`), then started (`start`: listening from then on).

    Args:
        host: the address to listen on (the loopback unless told otherwise).
        port: the port (0: any free one; `port` then says which).
        wait_for_client: seconds the first message waits for a client to subscribe (0: it
            does not wait), so that a viewer started with the run sees it from the start.
        backlog: messages queued per client; when a client falls further behind, its oldest
            queued message is dropped (the run never waits for a viewer).
    """

    fatal = False

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, wait_for_client: float = 0.0,
                 backlog: int = 1024):
        import foxglove
        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._channels: dict = {}
        self._latched: dict[str, tuple[bytes, int]] = {}
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self._wait = float(wait_for_client)
        self.host, self.port, self._backlog = host, port, int(backlog)
        self.server = None
        self.messages = 0

    def declare(self, specs: dict) -> None:
        """Makes the channels of `specs` (topic -> ChannelSpec), before `start`."""
        for topic, spec in specs.items():
            if topic not in self._channels:
                self._channel(topic, spec.type_name)

    def start(self) -> None:
        """Listens (once); OutputError, one line, when it cannot."""
        if self.server is not None:
            return
        try:
            self.server = self._foxglove.start_server(
                name="capsule_drake", host=self.host, port=self.port, context=self._context,
                server_listener=_listener(self), message_backlog_size=self._backlog)
        except Exception as e:   # a port in use, an address not this machine's
            reason = str(e).split(": ", 1)[-1]
            raise OutputError(f"--foxglove: cannot listen on {self.host}:{self.port} "
                              f"({reason}); give another port, or 0 for any free one") from None
        self.port = self.server.port

    @property
    def name(self) -> str:
        return f"the Foxglove server ws://{self.host}:{self.port}"

    def subscribed(self, topic: str) -> None:
        """A client subscribed to `topic`: a latched channel's last message is sent again,
        a moment later and twice more (RESEND_AFTER; logged here, it did not reach the
        client one time in two)."""
        with self._lock:
            latched = topic in self._latched
        for delay in RESEND_AFTER if latched else ():
            timer = threading.Timer(delay, self._resend, (topic,))
            timer.daemon = True
            timer.start()
        self._subscribed.set()

    def _resend(self, topic: str) -> None:
        with self._lock:
            latched = self._latched.get(topic)
            channel = self._channels.get(topic)
        if latched is not None and channel is not None:
            try:
                channel.log(latched[0], log_time=latched[1])
            except Exception:   # the server closed meanwhile: nothing to send to
                pass

    def _channel(self, topic: str, type_name: str):
        schema = self._foxglove.Schema(name=type_name, encoding="ros2msg",
                                       data=schema_text(type_name).encode())
        channel = self._foxglove.Channel(topic, schema=schema, message_encoding="cdr",
                                         context=self._context)
        with self._lock:
            self._channels[topic] = channel
        return channel

    def publish(self, topic: str, spec, message: dict, data: bytes, log_time_ns: int) -> None:
        if spec.latched:   # kept before the channel is advertised: a subscriber gets it
            with self._lock:
                self._latched[topic] = (data, log_time_ns)
        channel = self._channels.get(topic)
        if channel is None:   # not declared (the run declares all it writes)
            channel = self._channel(topic, spec.type_name)
        self.start()
        channel.log(data, log_time=log_time_ns)
        self.messages += 1
        if self._wait > 0.0:
            wait, self._wait = self._wait, 0.0
            deadline = time.monotonic() + wait
            while not self._subscribed.wait(0.05) and time.monotonic() < deadline:
                pass

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
