"""One reader interface over every recording format users bring.

rosbags' AnyReader reads ROS1 bags, ROS2 bag directories and bare ``.mcap`` / ``.db3`` files. A
truncated MCAP (a recorder killed mid-flight) has no footer and AnyReader refuses it, so those are
re-read record by record with the ``mcap`` package's stream reader, keeping every complete message
before the cut.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

from mapkit.ingest._errors import IngestError

log = logging.getLogger(__name__)

_MAGIC = {
    b"#ROSBAG V2.0": "ros1",
    b"\x89MCAP0\r\n": "mcap",
    b"SQLite format 3\x00": "db3",
}
_SUFFIX_KIND = {".bag": "ros1", ".mcap": "mcap", ".db3": "db3"}
FORMAT_NAMES = {
    "ros1": "ROS1 bag",
    "ros2": "ROS2 bag directory",
    "mcap": "MCAP file",
    "db3": "ROS2 sqlite3 file",
}


@dataclass(frozen=True)
class TopicSummary:
    """What one topic holds."""

    name: str
    msgtype: str
    count: int


@dataclass
class RawMessage:
    """One serialised message."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes | memoryview


@dataclass
class BagSummary:
    """Topics, counts and time span of one recording."""

    path: Path
    kind: str
    start_ns: int
    end_ns: int
    topics: dict[str, TopicSummary]
    warnings: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return max(self.end_ns - self.start_ns, 0) / 1e9

    @property
    def format_name(self) -> str:
        return FORMAT_NAMES[self.kind]


def normalize_topic(name: str) -> str:
    """Topic names compare with or without a leading slash."""
    return "/" + name.strip().lstrip("/")


def detect_kind(path: Path) -> str:
    """'ros1' | 'ros2' | 'mcap' | 'db3' for a recording path, or an IngestError saying why not."""
    if not path.exists():
        raise IngestError(f"input {str(path)!r} does not exist; check the path")
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return "ros2"
        storage = sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
        hint = f" (it holds {', '.join(storage)}: pass that file directly)" if storage else ""
        raise IngestError(f"directory {str(path)!r} is not a ROS2 bag: no metadata.yaml{hint}")
    with open(path, "rb") as f:
        head = f.read(16)
    if not head:
        raise IngestError(f"input {str(path)!r} is empty (0 bytes)")
    by_magic = next((kind for magic, kind in _MAGIC.items() if head.startswith(magic)), None)
    by_suffix = _SUFFIX_KIND.get(path.suffix.lower())
    if by_magic is None:
        expected = "a ROS1 .bag, a ROS2 bag directory, an .mcap or a .db3 file"
        raise IngestError(
            f"input {str(path)!r} is not a recording mapkit reads (starts with {head[:8]!r}); "
            f"expected {expected}"
        )
    if by_suffix != by_magic:
        raise IngestError(
            f"input {str(path)!r} holds a {FORMAT_NAMES[by_magic]} but is named {path.suffix or 'without suffix'}; "
            f"rename it to end in {next(s for s, k in _SUFFIX_KIND.items() if k == by_magic)}"
        )
    return by_magic


def _default_typestore(kind: str) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


class Source:
    """An open recording: summary, filtered message iteration and deserialisation."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.kind = detect_kind(self.path)
        self._reader: Any = None
        self._stream: _McapStream | None = None
        self.summary: BagSummary

    # -- lifecycle
    def __enter__(self) -> "Source":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        from rosbags.highlevel import AnyReader

        reader = AnyReader([self.path], default_typestore=_default_typestore(self.kind))
        try:
            reader.open()
        except Exception as exc:  # rosbags raises several unrelated types for damaged files
            if self.kind == "mcap":
                log.debug("AnyReader refused %s (%s); reading it as a stream", self.path, exc)
                self._stream = _McapStream(self.path)
                self.summary = self._stream.summary
                return
            raise IngestError(f"cannot read {str(self.path)!r} as a {FORMAT_NAMES[self.kind]}: {exc}") from None
        self._reader = reader
        topics: dict[str, TopicSummary] = {}
        for conn in reader.connections:
            name = normalize_topic(conn.topic)
            prev = topics.get(name)
            count = conn.msgcount + (prev.count if prev else 0)
            topics[name] = TopicSummary(name, conn.msgtype, count)
        self.summary = BagSummary(
            self.path, self.kind, int(reader.start_time), int(reader.end_time), topics
        )

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    # -- reading
    def messages(self, topics: Iterable[str]) -> Iterator[RawMessage]:
        """Messages of the given topics in log-time order."""
        wanted = {normalize_topic(t) for t in topics}
        if self._stream is not None:
            yield from self._stream.messages(wanted)
            return
        conns = [c for c in self._reader.connections if normalize_topic(c.topic) in wanted]
        if not conns:
            return
        count = 0
        it = self._reader.messages(connections=conns)
        while True:
            try:
                conn, stamp, data = next(it)
            except StopIteration:
                return
            except Exception as exc:  # damaged chunk/record: name the file and where
                raise IngestError(
                    f"{str(self.path)!r} is damaged after message {count} ({type(exc).__name__}: {exc}); "
                    "re-export the recording or repair it (for MCAP: `mcap recover`)"
                ) from None
            count += 1
            yield RawMessage(normalize_topic(conn.topic), conn.msgtype, int(stamp), data)

    def deserialize(self, msg: RawMessage) -> Any:
        try:
            if self._stream is not None:
                return self._stream.typestore.deserialize_cdr(msg.data, msg.msgtype)
            return self._reader.deserialize(msg.data, msg.msgtype)
        except Exception as exc:
            raise IngestError(
                f"{str(self.path)!r}: a {msg.msgtype} message on {msg.topic} at log time "
                f"{msg.log_time_ns} ns does not deserialise ({exc}); the recording is damaged"
            ) from None


class _McapStream:
    """Reads a footer-less (truncated) MCAP record by record; keeps what precedes the cut."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path = path
        self.typestore = get_typestore(Stores.EMPTY)
        self._channels: dict[int, tuple[str, str]] = {}
        counts: dict[str, list[Any]] = {}
        start, end, n, cut = None, None, 0, None
        types: dict[str, Any] = {}
        for record in self._records():
            if isinstance(record, _cut_marker):
                cut = record
                break
            kind = type(record).__name__
            if kind == "Schema":
                if record.encoding != "ros2msg":
                    raise IngestError(
                        f"{str(path)!r}: schema {record.name!r} is encoded as {record.encoding!r}; "
                        "mapkit reads ROS2 CDR MCAP files (ros2msg schemas)"
                    )
                types.update(get_types_from_msg(record.data.decode(), _ros2_typename(record.name)))
            elif kind == "Channel":
                self._channels[record.id] = (normalize_topic(record.topic), record.schema_id)
            elif kind == "Message":
                n += 1
                start = record.log_time if start is None else min(start, record.log_time)
                end = record.log_time if end is None else max(end, record.log_time)
                topic = self._channels[record.channel_id][0]
                counts.setdefault(topic, [record.channel_id, 0])[1] += 1
        self.typestore.register(types)
        self._schema_names: dict[int, str] = {}
        for record in self._records():
            if type(record).__name__ == "Schema":
                self._schema_names[record.id] = _ros2_typename(record.name)
        topics = {
            t: TopicSummary(t, self._schema_names[self._channels[cid][1]], c)
            for t, (cid, c) in counts.items()
        }
        warnings = []
        if cut is not None:
            warnings.append(
                f"{str(path)!r} is truncated or damaged: the record at byte {cut.offset} of "
                f"{path.stat().st_size} is incomplete ({cut.reason}); recovered {n} complete messages before it"
            )
            log.info(warnings[-1])
        if n == 0:
            raise IngestError(f"{str(path)!r} holds no readable messages (MCAP damaged or truncated before the first message)")
        self.summary = BagSummary(path, "mcap", int(start), int(end), topics, warnings)

    def _records(self) -> Iterator[Any]:
        from mcap.stream_reader import StreamReader

        with open(self.path, "rb") as f:
            it = StreamReader(f, skip_magic=False, emit_chunks=False).records
            record_start = f.tell()
            while True:
                try:
                    record = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # EndOfFile, bad CRC, bad opcode: the damaged tail
                    yield from _partial_chunk_records(self.path, record_start)
                    yield _cut_marker(record_start, f"{type(exc).__name__}: {exc}".rstrip(": "))
                    return
                yield record
                record_start = f.tell()

    def messages(self, wanted: set[str]) -> Iterator[RawMessage]:
        for record in self._records():
            if type(record).__name__ != "Message":
                continue
            topic, schema_id = self._channels[record.channel_id]
            if topic in wanted:
                yield RawMessage(topic, self._schema_names[schema_id], int(record.log_time), record.data)


@dataclass
class _cut_marker:
    offset: int
    reason: str


def _ros2_typename(name: str) -> str:
    """MCAP schema names are 'pkg/msg/Type' (ROS2) or sometimes 'pkg/Type'."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _partial_chunk_records(path: Path, offset: int) -> Iterator[Any]:
    """Complete records inside a chunk that the file cut off (the writer died mid-chunk).

    The mcap package only parses whole chunks, so the chunk header is read here (MCAP spec:
    opcode 0x06; start/end time, uncompressed size, CRC, compression, records length) and the
    available compressed bytes are decompressed as a stream.
    """
    import io
    import struct

    from mcap.stream_reader import StreamReader

    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read()
    if len(data) < 9 + 32 or data[0] != 0x06:
        return
    pos = 9 + 8 + 8 + 8 + 4
    (clen,) = struct.unpack_from("<I", data, pos)
    compression = data[pos + 4 : pos + 4 + clen].decode(errors="replace")
    pos += 4 + clen + 8
    payload = data[pos:]
    try:
        if compression == "":
            records = payload
        elif compression == "zstd":
            import zstandard

            records = zstandard.ZstdDecompressor().decompressobj().decompress(payload)
        elif compression == "lz4":
            import lz4.frame

            records = lz4.frame.LZ4FrameDecompressor().decompress(payload)
        else:
            return
    except Exception:  # the cut fell inside the compressed frame's header: nothing to save
        return
    it = StreamReader(io.BytesIO(records), skip_magic=True).records
    while True:
        try:
            record = next(it)
        except Exception:  # StopIteration or the cut record
            return
        yield record
