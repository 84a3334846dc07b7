"""Two snapshot slots: a builder fills the back one while readers use the front one."""
from __future__ import annotations

import threading
from contextlib import contextmanager


class DoubleBuffer:
    """Front/back slots with reader counts.

    The single builder calls ``back()`` (which waits until no reader still holds that slot),
    fills it, then ``publish()``; readers hold the front slot with ``with buf.read() as slot``
    and always see a complete snapshot. Publishing never waits for readers.
    """

    def __init__(self, slots):
        self.slots = list(slots)
        assert len(self.slots) == 2
        self._front = 0
        self._readers = [0, 0]
        self._cv = threading.Condition()

    @property
    def front_index(self) -> int:
        return self._front

    def back(self, timeout: float | None = None) -> int:
        """Index of the slot the builder may overwrite now."""
        b = 1 - self._front
        with self._cv:
            if not self._cv.wait_for(lambda: self._readers[b] == 0, timeout):
                raise TimeoutError(f"snapshot slot {b} still held by a reader after {timeout} s")
        return b

    def publish(self, i: int) -> None:
        with self._cv:
            self._front = i

    @contextmanager
    def read(self):
        with self._cv:
            i = self._front
            self._readers[i] += 1
        try:
            yield self.slots[i]
        finally:
            with self._cv:
                self._readers[i] -= 1
                self._cv.notify_all()
