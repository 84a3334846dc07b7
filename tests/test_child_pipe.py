"""The helper processes' control pipe (service/child_pipe.py): messages framed and read back in
order, and the child's inbox, which a thread fills until ``close`` or the end of the stream."""
import io

from pointfence.service.child_pipe import control_inbox, receive, send


def _stream(*msgs) -> io.BytesIO:
    buf = io.BytesIO()
    for m in msgs:
        send(buf, m)
    buf.seek(0)
    return buf


def test_messages_come_back_in_order_then_none_at_the_end():
    fh = _stream(("init", {"a": 1}), ("flush",))
    assert receive(fh) == ("init", {"a": 1})
    assert receive(fh) == ("flush",)
    assert receive(fh) is None


def test_the_inbox_ends_at_close_and_reads_nothing_after_it():
    inbox = control_inbox(_stream(("mark", 3), ("close",), ("after",)), "test-control")
    got = [inbox.get(timeout=5) for _ in range(2)]
    assert got == [("mark", 3), ("close",)]
    assert inbox.empty()


def test_the_inbox_says_none_when_the_service_is_gone():
    inbox = control_inbox(_stream(("mark", 1)), "test-control")
    assert inbox.get(timeout=5) == ("mark", 1)
    assert inbox.get(timeout=5) is None
