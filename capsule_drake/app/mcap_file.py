"""The MCAP file a run writes (`outputs.mcap`, `--mcap FILE`): ROS 2 messages as rosbag2
writes them (profile ros2, ros2msg schemas, CDR), chunked and compressed as it goes, finished
whole however the run ends. The channels and what they hold: app/mcap_log.py.
"""

import contextlib
import errno
import os
import stat
from pathlib import Path

from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer
# mcap_ros2's own Writer uses this to encode; it has no public encoder and registers its
# channels without the QoS metadata rosbag2 replays from.
from mcap_ros2._dynamic import serialize_dynamic

from capsule_drake.app.outputs import MCAP_LIBRARY, check_file_output, is_capsule_mcap
from capsule_drake.app.ros2_messages import offered_qos_profiles, schema_text



def check_mcap_path(path, replace: bool | None = False, expected_bytes: float = 0.0) -> Path:
    """The file `--mcap` names, checked before anything is simulated (app/outputs.py's
    `check_file_output`): a regular file or a new one, not a link, in a folder that exists
    and can be written, with room for `expected_bytes`; an existing file is refused unless
    `replace` (None: the command has no --force to offer) and it is an MCAP log this
    simulator wrote. The command line checks it with its other outputs (`plan_outputs`).
    Raises OutputError (one line)."""
    return check_file_output(path, "--mcap", replace=replace, previous=is_capsule_mcap,
                             previous_name="an MCAP log written by capsule-sim",
                             expected_bytes=expected_bytes)


class McapWriteError(OSError):
    """Writing the MCAP log failed (a full disk, an I/O error, a file size limit): one line
    naming the file; the file is left as far as it was written, unless that is not even
    its header (then it is removed: `Ros2McapFile._failed`)."""


class Ros2McapFile:
    """An MCAP file of ROS 2 messages (profile ros2, schemas ros2msg, messages CDR) being
    written: each type's schema and each topic's channel registered at its first message,
    the channel with the QoS rosbag2 replays it with; messages are gathered into chunks
    (`chunk_size` bytes, compressed) that are written as they fill.

    The file is created at the first message; `close()` finishes it (idempotent). A write
    that fails (at a message, or when the file is finished, flushed and synced) raises
    McapWriteError once, naming the file, and leaves `error` set; the file is closed and
    later messages are refused. A file that failed before its header was on disk is
    removed: it holds nothing to read, and the retry's --force (which replaces only an MCAP
    log of this simulator's) would refuse it.
    """

    def __init__(self, path, compression: str = "zstd", chunk_size: int = 1 << 20):
        self.path = Path(path)
        self._compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                             "none": CompressionType.NONE}[compression]
        self._chunk_size = int(chunk_size)
        self._stream = None
        self._writer = None
        self._schemas = {}    # type name -> (schema id, encoder)
        self._channels = {}   # topic -> (channel id, encoder, type name)
        self.messages = 0
        self.created = False  # whether this created (or emptied) the file at `path`
        self.closed = False
        self.error: str | None = None  # why writing failed (one line), or None

    def _open(self):
        # Not through a symbolic link, and without blocking on a named pipe (no reader:
        # ENXIO); only a regular file is written (the command line checked the path, but
        # it may have changed since).
        flags = (os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK
                 | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        fd = os.open(self.path, flags, 0o666)
        self.created = True
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise OSError(errno.EINVAL, "not a regular file")
        os.set_blocking(fd, True)
        stream = os.fdopen(fd, "wb")
        try:
            writer = Writer(stream, chunk_size=self._chunk_size, compression=self._compression)
            writer.start(profile=Profile.ROS2, library=MCAP_LIBRARY)
            # rosbag2 reads the channels' QoS with the metadata format its "rosbag2" record
            # names; an empty one means version 8 and before: integer policies (ros2_messages).
            writer.add_metadata("rosbag2", {"serialized_metadata": ""})
        except BaseException:
            with contextlib.suppress(OSError):
                stream.close()
            raise
        self._stream, self._writer = stream, writer

    def _channel(self, topic: str, type_name: str, latched: bool):
        if self._writer is None:
            self._open()
        if type_name not in self._schemas:
            text = schema_text(type_name)
            schema_id = self._writer.register_schema(type_name, SchemaEncoding.ROS2,
                                                     text.encode())
            self._schemas[type_name] = (schema_id, serialize_dynamic(type_name, text)[type_name])
        schema_id, encoder = self._schemas[type_name]
        channel_id = self._writer.register_channel(
            topic, MessageEncoding.CDR, schema_id,
            {"offered_qos_profiles": offered_qos_profiles(latched, depth=1 if latched else 10)})
        self._channels[topic] = (channel_id, encoder, type_name)
        return self._channels[topic]

    # As an output of a ChannelWriter (app/channels.py): a failure stops the run.
    fatal = True

    @property
    def name(self) -> str:
        return f"the MCAP log {self.path}"

    def write(self, topic: str, type_name: str, message: dict, log_time_ns: int,
              latched: bool = False):
        """Encodes `message` (a dict of the type's fields) and adds it to `topic`."""
        self._add(topic, type_name, latched, message, None, log_time_ns)

    def publish(self, topic: str, spec, message: dict, data: bytes, log_time_ns: int):
        """Adds a message the ChannelWriter encoded (`data`, CDR) to `topic`."""
        self._add(topic, spec.type_name, spec.latched, message, data, log_time_ns)

    def _add(self, topic, type_name, latched, message, data, log_time_ns):
        if self.closed or self.error is not None:
            raise RuntimeError(f"{self.path}: the MCAP log is closed")
        try:
            channel = self._channels.get(topic) or self._channel(topic, type_name, latched)
            channel_id, encoder, known_type = channel
            if known_type != type_name:
                raise ValueError(f"topic {topic} carries {known_type}, not {type_name}")
            self._writer.add_message(channel_id, log_time=log_time_ns,
                                     data=encoder(message) if data is None else data,
                                     publish_time=log_time_ns, sequence=self.messages)
        except OSError as e:
            raise self._failed(e) from None
        self.messages += 1

    def _failed(self, e: OSError) -> McapWriteError:
        """Notes a failed write, closes the file (dropping what is unwritten; removing it
        if not even its header is on disk) and returns the error to raise."""
        stream, self._writer, self._stream = self._stream, None, None
        if stream is not None:
            with contextlib.suppress(OSError):  # its flush fails again; the file is closed
                stream.close()
        if self.error is None:
            kept = "the file is incomplete"
            if (self.created and self.path.is_file() and not self.path.is_symlink()
                    and not is_capsule_mcap(self.path)):
                with contextlib.suppress(OSError):
                    self.path.unlink()
                    kept = "nothing of it could be kept (removed)"
            reason = e.strerror or str(e)
            self.error = (f"{self.path}: could not write the MCAP log ({reason}) after "
                          f"{self.messages} messages; {kept}")
        return McapWriteError(self.error)

    def close(self):
        """Writes the last chunk, the summary and the footer, flushes and syncs the file
        and closes it, which is closed even if finishing it fails (McapWriteError, once).
        Idempotent: later calls do nothing, as does a close after a write that failed."""
        if self.closed:
            return
        self.closed = True
        if self.error is not None:
            return
        writer, stream = self._writer, self._stream
        try:
            if writer is not None:
                writer.finish()
            if stream is not None:
                stream.flush()
                os.fsync(stream.fileno())
        except OSError as e:
            raise self._failed(e) from None
        finally:
            self._writer = None
            if self._stream is not None:
                self._stream = None
                try:
                    stream.close()
                except OSError as e:
                    raise self._failed(e) from None


# --- What is logged: one stream per source, each read by its own periodic event ------------
