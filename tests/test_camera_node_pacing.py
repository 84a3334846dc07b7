"""`pointfence ros2 camera-node`'s pacing of a file source (no ROS needed: the loop is given a
publisher): each frame is read ahead of its deadline, so its stamp (the moment it is due) comes
after its read has finished and the publication follows the stamp at once."""
import threading
import time

from pointfence.service.ros2.camera_node import _loop


class SlowFile:
    """A file source whose every read takes ``read_s`` (a PNG decode); logs when each ended."""
    realtime = False
    ended = False

    def __init__(self, n, read_s):
        self.n, self.read_s, self.i, self.read_done = n, read_s, 0, []

    def read(self, timeout=None):
        if self.i >= self.n:
            return None
        time.sleep(self.read_s)
        self.i += 1
        self.read_done.append(time.time())
        return self.i - 1         # (the frame: its index)


class Log:
    def __init__(self):
        self.published, self.stamps = 0, []

    def publish(self, frame, read_at=None):
        self.stamps.append((frame, read_at))
        self.published += 1
        return read_at


def test_file_frames_are_read_before_their_deadline_and_stamped_when_due():
    src, pub = SlowFile(6, read_s=0.02), Log()
    _loop(src, pub, rate=20.0, frames=0, stop=threading.Event())
    assert [f for f, _ in pub.stamps] == list(range(6))          # every frame, in order, then the end
    for frame, stamp in pub.stamps:
        assert src.read_done[frame] <= stamp, "a frame was stamped before it had been read"
    stamps = [s for _, s in pub.stamps]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))


def test_frames_limit_reads_no_frame_beyond_it():
    src, pub = SlowFile(10, read_s=0.0), Log()
    _loop(src, pub, rate=200.0, frames=3, stop=threading.Event())
    assert pub.published == 3 and src.i == 3
