"""Which recorder a service gets: none, in memory, a streamed ``.pfrec`` (``record.Recorder``)
or an MCAP file with ROS 2 schemas (``mcap_record.McapRecorder``)."""
from __future__ import annotations

from .record import Recorder


def make_recorder(n: int, keep: int = 0, path=None, rate_hz: float = 1000.0):
    """The service's recorder: None (no recording), ``keep`` ticks in memory, a streamed
    ``.pfrec`` (``Recorder``), or an MCAP file with ROS 2 schemas (``path`` ending in ``.mcap``:
    ``mcap_record.McapRecorder``, which also keeps ``keep`` ticks in memory)."""
    if path is not None and str(path).endswith(".mcap"):
        from .mcap_record import McapRecorder

        return McapRecorder(path, n, keep=keep, rate_hz=rate_hz)
    if path is not None:
        return Recorder(n=n, path=path)
    return Recorder(keep, n) if keep else None


__all__ = ["make_recorder"]
