"""One reader interface over every recording format: rosbags' AnyReader for ROS1 bags, ROS2 bag
directories and ``.db3`` files; the ``mcap`` package for ``.mcap``, record by record when the file was cut
off (no footer), keeping every complete message before the cut."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapkit._threads import prefetch
from mapkit.ingest._errors import IngestError

log = logging.getLogger(__name__)

_MAGIC = {b"#ROSBAG V2.0": "ros1", b"\x89MCAP0\r\n": "mcap", b"SQLite format 3\x00": "db3"}
_SUFFIX_KIND = {".bag": "ros1", ".mcap": "mcap", ".db3": "db3"}
FORMAT_NAMES = {"ros1": "ROS1 bag", "ros2": "ROS2 bag directory", "mcap": "MCAP file", "db3": "ROS2 sqlite3 file"}


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
        raise IngestError(f"input {str(path)!r} is not a recording mapkit reads (starts with {head[:8]!r}); "
                          f"expected {expected}")
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
        self._backend: Any = None
        self.summary: BagSummary

    def __enter__(self) -> Source:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        if self.kind == "mcap":
            # The mcap package reads indexed MCAP faster than rosbags (zstandard, no CRC pass);
            # a file without a usable summary (cut off while recording) is read as a stream.
            try:
                self._backend = _McapIndexed(self.path)
            except _NoSummary as exc:
                log.debug("%s has no usable summary (%s); reading it as a stream", self.path, exc)
                self._backend = _McapStream(self.path)
        else:
            self._backend = _Rosbags(self.path, self.kind)
        self.summary = self._backend.summary

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()
            self._backend = None

    def messages(self, topics: Iterable[str]) -> Iterator[RawMessage]:
        """Messages of the given topics in log-time order."""
        wanted = {normalize_topic(t) for t in topics}
        count = 0
        it = self._backend.messages(wanted)
        while True:
            try:
                msg = next(it)
            except StopIteration:
                return
            except IngestError:
                raise
            except Exception as exc:  # noqa: BLE001 - damaged chunk/record: name the file and where
                raise IngestError(f"{str(self.path)!r} is damaged after message {count} ({type(exc).__name__}: {exc}); "
                                  "re-export the recording or repair it (for MCAP: `mcap recover`)") from None
            count += 1
            yield msg

    def deserialize(self, msg: RawMessage) -> Any:
        try:
            return self._backend.deserialize(msg)
        except Exception as exc:  # noqa: BLE001 - a deserializer raises many kinds for a malformed message
            raise IngestError(f"{str(self.path)!r}: a {msg.msgtype} message on {msg.topic} at log time "
                              f"{msg.log_time_ns} ns does not deserialise ({exc}); the recording is damaged") from None


class _Rosbags:
    """ROS1 bags, ROS2 bag directories and bare .db3 files through rosbags' AnyReader."""

    def __init__(self, path: Path, kind: str) -> None:
        from rosbags.highlevel import AnyReader

        reader = AnyReader([path], default_typestore=_default_typestore(kind))
        try:
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises several unrelated types for damaged files
            why = " ".join(str(exc).split())  # YAML errors span several lines
            if kind == "ros1" and "index" in why.lower():
                why += ("; the index at the end of the bag is missing or cut off (was the recorder killed?): rebuild "
                        "it with `rosbag reindex` and run again")
            elif kind == "ros2" and "yaml" in type(exc).__name__.lower() + why.lower():
                why = f"its metadata.yaml does not parse ({why}); restore it or regenerate it with `ros2 bag reindex`"
            raise IngestError(f"cannot read {str(path)!r} as a {FORMAT_NAMES[kind]}: {why}") from None
        self._reader = reader
        topics: dict[str, TopicSummary] = {}
        for conn in reader.connections:
            name = normalize_topic(conn.topic)
            prev = topics.get(name)
            topics[name] = TopicSummary(name, conn.msgtype, conn.msgcount + (prev.count if prev else 0))
        self.summary = BagSummary(path, kind, int(reader.start_time), int(reader.end_time), topics)

    def close(self) -> None:
        self._reader.close()

    def messages(self, wanted: set[str]) -> Iterator[RawMessage]:
        conns = [c for c in self._reader.connections if normalize_topic(c.topic) in wanted]
        if conns:
            for conn, stamp, data in self._reader.messages(connections=conns):
                yield RawMessage(normalize_topic(conn.topic), conn.msgtype, int(stamp), data)

    def deserialize(self, msg: RawMessage) -> Any:
        return self._reader.deserialize(bytes(msg.data), msg.msgtype)  # rosbags hands out bytes: bytes() returns them as they are


class _NoSummary(Exception):
    pass


def _typestore_from_schemas(path: Path, schemas: Iterable[Any]) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    types: dict[str, Any] = {}
    for schema in schemas:
        if schema.encoding != "ros2msg":
            raise IngestError(f"{str(path)!r}: schema {schema.name!r} is encoded as {schema.encoding!r}; "
                              "mapkit reads ROS2 CDR MCAP files (ros2msg schemas)")
        types.update(get_types_from_msg(schema.data.decode(), _ros2_typename(schema.name)))
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


class _McapIndexed:
    """A complete MCAP file, read through its summary section and chunk indexes."""

    def __init__(self, path: Path) -> None:
        from mcap.reader import make_reader

        self.path = path
        self._file = open(path, "rb")  # noqa: SIM115 - held until close()
        try:
            self._reader = make_reader(self._file)
            summary = self._reader.get_summary()
        except Exception as exc:  # noqa: BLE001 - any failure to read the summary: fall back to a linear scan
            self._file.close()
            raise _NoSummary(str(exc)) from None
        if summary is None or summary.statistics is None or not summary.chunk_indexes:
            self._file.close()
            raise _NoSummary("no summary section")
        self._summary = summary
        self._names = {sid: _ros2_typename(s.name) for sid, s in summary.schemas.items()}
        self.typestore = _typestore_from_schemas(path, summary.schemas.values())
        counts = summary.statistics.channel_message_counts
        topics: dict[str, TopicSummary] = {}
        for cid, ch in summary.channels.items():
            name = normalize_topic(ch.topic)
            prev = topics.get(name)
            topics[name] = TopicSummary(name, self._names[ch.schema_id], counts.get(cid, 0) + (prev.count if prev else 0))
        st = summary.statistics
        self.summary = BagSummary(path, "mcap", int(st.message_start_time), int(st.message_end_time), topics)

    def close(self) -> None:
        self._file.close()

    def messages(self, wanted: set[str]) -> Iterator[RawMessage]:
        summary = self._summary
        channels = {cid: ch for cid, ch in summary.channels.items() if normalize_topic(ch.topic) in wanted}
        if not channels:
            return
        chunks = sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset))
        overlapping = any(b.message_start_time < a.message_end_time for a, b in itertools.pairwise(chunks))
        if overlapping or any(c.compression not in ("", "zstd", "lz4") for c in chunks):
            # Interleaved chunks need the mcap package's merge by log time.
            names = [ch.topic for ch in channels.values()]
            for schema, channel, message in self._reader.iter_messages(topics=names, log_time_order=True):
                if schema is None:  # every channel kept above has one (its schema named the type)
                    raise IngestError(f"{str(self.path)!r}: channel {channel.topic!r} has no schema")
                yield RawMessage(normalize_topic(channel.topic), self._names[schema.id], int(message.log_time), message.data)
            return
        topics = {cid: (normalize_topic(ch.topic), self._names[ch.schema_id]) for cid, ch in channels.items()}
        for records in prefetch(_decompressed_chunks(self.path, chunks), depth=3):
            batch = []
            for cid, log_time, data in _iter_message_records(records):
                if cid in topics:
                    batch.append((log_time, cid, data))
            batch.sort(key=lambda m: m[0])
            for log_time, cid, data in batch:
                topic, msgtype = topics[cid]
                yield RawMessage(topic, msgtype, log_time, data)

    def deserialize(self, msg: RawMessage) -> Any:
        return self.typestore.deserialize_cdr(msg.data, msg.msgtype)


class _McapStream:
    """Reads a footer-less (truncated) MCAP record by record; keeps what precedes the cut."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._channels: dict[int, tuple[str, str]] = {}
        self._cut: tuple[int, str] | None = None
        """(byte offset, why) of the first incomplete record, once the records have been read."""
        counts: dict[str, list[Any]] = {}
        start, end, n = None, None, 0
        schemas: list[Any] = []
        for record in self._records():
            kind = type(record).__name__
            if kind == "Schema":
                schemas.append(record)
            elif kind == "Channel":
                self._channels[record.id] = (normalize_topic(record.topic), record.schema_id)
            elif kind == "Message":
                n += 1
                start = record.log_time if start is None else min(start, record.log_time)
                end = record.log_time if end is None else max(end, record.log_time)
                topic = self._channels[record.channel_id][0]
                counts.setdefault(topic, [record.channel_id, 0])[1] += 1
        self.typestore = _typestore_from_schemas(path, schemas)
        self._schema_names = {sch.id: _ros2_typename(sch.name) for sch in schemas}
        topics = {t: TopicSummary(t, self._schema_names[self._channels[cid][1]], c) for t, (cid, c) in counts.items()}
        warnings: list[str] = []
        if self._cut is not None:
            warnings.append(f"{str(path)!r} is truncated or damaged: the record at byte {self._cut[0]} of "
                            f"{path.stat().st_size} is incomplete ({self._cut[1]}); recovered {n} complete messages "
                            "before it")
            log.info(warnings[-1])
        if n == 0:
            raise IngestError(f"{str(path)!r} holds no readable messages (MCAP damaged or truncated before the first message)")
        assert start is not None and end is not None  # set by the first message
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
                except Exception as exc:  # noqa: BLE001 - EndOfFile, bad CRC, bad opcode: the damaged tail
                    yield from _partial_chunk_records(self.path, record_start)
                    self._cut = (record_start, f"{type(exc).__name__}: {exc}".rstrip(": "))
                    return
                yield record
                record_start = f.tell()

    def close(self) -> None:
        pass

    def deserialize(self, msg: RawMessage) -> Any:
        return self.typestore.deserialize_cdr(msg.data, msg.msgtype)

    def messages(self, wanted: set[str]) -> Iterator[RawMessage]:
        for record in self._records():
            if type(record).__name__ != "Message":
                continue
            topic, schema_id = self._channels[record.channel_id]
            if topic in wanted:
                yield RawMessage(topic, self._schema_names[schema_id], int(record.log_time), record.data)


def _ros2_typename(name: str) -> str:
    """MCAP schema names are 'pkg/msg/Type' (ROS2) or sometimes 'pkg/Type'."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _partial_chunk_records(path: Path, offset: int) -> Iterator[Any]:
    """Complete records inside a chunk that the file cut off (the writer died mid-chunk): the chunk header
    (MCAP opcode 0x06) read here, the available compressed bytes decompressed as a stream."""
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
    except Exception:  # noqa: BLE001 - the cut fell inside the compressed frame's header: nothing to save
        return
    it = StreamReader(io.BytesIO(records), skip_magic=True).records
    while True:
        try:
            record = next(it)
        except Exception:  # noqa: BLE001 - StopIteration or the cut record
            return
        yield record


def _decompressed_chunks(path: Path, chunks: list[Any]) -> Iterator[bytes]:
    """The records section of each chunk, decompressed in the prefetch thread (reading and decompressing
    release the GIL; the mcap package's iterator would also parse there, holding it)."""
    import struct

    import lz4.frame
    import zstandard

    zstd = zstandard.ZstdDecompressor()
    with open(path, "rb") as f:
        for index in chunks:
            f.seek(index.chunk_start_offset)
            raw = f.read(index.chunk_length)
            if len(raw) < index.chunk_length or raw[0] != 0x06:
                raise IngestError(f"{str(path)!r}: chunk at byte {index.chunk_start_offset} is damaged or missing")
            pos = 9 + 8 + 8
            uncompressed_size, _crc, clen = struct.unpack_from("<QII", raw, pos)
            pos += 16 + clen
            (records_len,) = struct.unpack_from("<Q", raw, pos)
            records = raw[pos + 8 : pos + 8 + records_len]
            if index.compression == "zstd":
                records = zstd.decompress(records, max_output_size=uncompressed_size)
            elif index.compression == "lz4":
                records = lz4.frame.decompress(records)
            yield records


def _iter_message_records(records: bytes) -> Iterator[tuple[int, int, memoryview]]:
    """(channel id, log time, data) of each Message record (opcode 0x05) in a chunk's records."""
    import struct

    view = memoryview(records)
    unpack = struct.unpack_from
    pos, end = 0, len(records)
    while pos + 9 <= end:
        opcode = records[pos]
        (length,) = unpack("<Q", records, pos + 1)
        body = pos + 9
        if opcode == 0x05:
            channel_id, _seq, log_time, _pub = unpack("<HIQQ", records, body)
            yield channel_id, log_time, view[body + 22 : body + length]
        pos = body + length
