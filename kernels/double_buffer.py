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
        self._waiting = 0   # builders waiting in back(): only then does a release notify
        # (readers take the lock itself: a Condition's own enter and exit are Python code)
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)

    @property
    def front_index(self) -> int:
        return self._front

    def back(self, timeout: float | None = None) -> int:
        """Index of the slot the builder may overwrite now."""
        b = 1 - self._front
        with self._cv:
            self._waiting += 1
            try:
                free = self._cv.wait_for(lambda: self._readers[b] == 0, timeout)
            finally:
                self._waiting -= 1
            if not free:
                raise TimeoutError(f"snapshot slot {b} still held by a reader after {timeout} s")
        return b

    def publish(self, i: int) -> None:
        with self._cv:
            self._front = i

    def acquire(self) -> int:
        """Hold the front slot for reading (the builder will not overwrite it); its index. The
        1 kHz tick's form of ``read()`` (a generator-based context manager costs microseconds);
        pair it with ``release``."""
        with self._lock:
            i = self._front
            self._readers[i] += 1
        return i

    def release(self, i: int) -> None:
        """Let go of slot ``i`` (from ``acquire``)."""
        with self._lock:
            self._readers[i] -= 1
            if self._waiting:
                self._cv.notify_all()

    @contextmanager
    def read(self):
        i = self.acquire()
        try:
            yield self.slots[i]
        finally:
            self.release(i)
