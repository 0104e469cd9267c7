"""`mapkit fly --record`: every message in and out, as the CDR that crossed the link, in one MCAP file
(ROS 2 schemas from the same typestore), readable by `mapkit info`, `mapkit ingest` and Foxglove."""

from __future__ import annotations

import threading
from pathlib import Path

from mapkit.fly._errors import FlyError
from mapkit.fly._msgs import typestore


class Recording:
    """An MCAP file being written from several threads; :meth:`close` finishes it (its summary and index)."""

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise FlyError(f"record path {str(self.path)!r} must end in .mcap")
        try:
            self._file = self.path.open("wb")
        except OSError as exc:
            raise FlyError(f"cannot write the recording {str(self.path)!r}: {exc.strerror}; pick a writable path") from None
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="mapkit fly")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self.messages = 0

    def _channel(self, topic: str, msgtype: str) -> int:
        if msgtype not in self._schemas:
            text = typestore().generate_msgdef(msgtype, ros_version=2)[0]
            self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", text.encode())
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schemas[msgtype])
        return self._channels[topic]

    def write(self, topic: str, msgtype: str, raw: bytes, log_time_ns: int) -> None:
        """One message as it crossed the link (topic: the ROS 2 name)."""
        with self._lock:
            if self._file.closed:
                return
            self._writer.add_message(self._channel(topic, msgtype), log_time=log_time_ns, data=raw,
                                     publish_time=log_time_ns)
            self.messages += 1

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._writer.finish()
                self._file.close()
