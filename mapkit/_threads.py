"""Background read-ahead shared by the stages that stream data from disk."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any


def prefetch(iterator: Iterator[Any], depth: int = 8) -> Iterator[Any]:
    """Run `iterator` in a background thread, `depth` items ahead (decompression releases the GIL); its
    exceptions are re-raised in the consumer, and stopping early stops the thread."""
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
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, who re-raises it
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

