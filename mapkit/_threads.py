"""Background read-ahead shared by the stages that stream data from disk."""

from __future__ import annotations

from typing import Any, Iterator


def prefetch(iterator: Iterator[Any], depth: int = 8) -> Iterator[Any]:
    """Run `iterator` in a background thread, `depth` items ahead.

    Chunk decompression (zstd/lz4) releases the GIL, so reading overlaps the consumer's decoding
    on a second core. Exceptions are re-raised in the consumer; stopping early stops the thread.
    """
    import queue
    import threading

    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce() -> None:
        try:
            for item in iterator:
                while not stop.is_set():
                    try:
                        items.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            items.put((done, None))
        except BaseException as exc:  # handed to the consumer
            items.put((done, exc))

    thread = threading.Thread(target=produce, daemon=True, name="mapkit-prefetch")
    thread.start()
    try:
        while True:
            item, exc = items.get()
            if item is done:
                if exc is not None:
                    raise exc
                return
            yield item
    finally:
        stop.set()
        while thread.is_alive():
            try:
                items.get_nowait()
            except queue.Empty:
                thread.join(timeout=0.05)


def _decompressed_chunks(path: Path, chunks: list[Any]) -> Iterator[bytes]:
    """The records section of each chunk, decompressed (runs in the prefetch thread).

    Why not the mcap package's iterator: it parses every record in Python in the same thread
    that decompresses, so a reader thread would hold the GIL most of the time. Here the thread
    only reads and decompresses (both release the GIL) and the consumer parses.
    """
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
