"""One rclpy node with its own context, spun by an executor in its own thread.

Every ROS 2 part of pointfence (a camera source, a camera node, a CRTK arm's bridge, the
telemetry) owns one ``RosNode``: its callbacks run on the node's thread, never on the 1 kHz
haptic loop's, and they hand data over through the owner's own buffers. A context of its own
per node lets several nodes live in one process and be shut down independently (tests).
"""
from __future__ import annotations

import atexit
import threading
from typing import Optional

from ..osthread import name_this_thread
from . import dds


class RosNode:
    """An rclpy node named ``name`` (in ``namespace``), spun on a daemon thread after ``start()``.

    ``domain_id`` overrides ``ROS_DOMAIN_ID`` for this node's context only. ``executor``:
    ``"single"`` (rclpy's ``SingleThreadedExecutor``) or ``"events"`` (rclpy's
    ``EventsExecutor``, whose event queue is in C++: for topics at 1 kHz it spends a fraction of
    the Python time per message; it does not serve guard conditions, so a node on it publishes
    from its owner's thread). ``close()`` stops the executor, destroys the node and shuts the
    context down (idempotent)."""

    def __init__(self, name: str, namespace: str = "", domain_id: Optional[int] = None, executor: str = "single"):
        rclpy = dds.rclpy()
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        if executor not in ("single", "events"):
            raise ValueError(f"RosNode executor {executor!r}; expected 'single' or 'events'")

        self.context = Context()
        kw = {} if domain_id is None else {"domain_id": int(domain_id)}
        rclpy.init(context=self.context, **kw)
        try:
            self.node = rclpy.create_node(name, namespace=namespace or "", context=self.context)
            if executor == "events":
                from rclpy.experimental import EventsExecutor

                self.executor = EventsExecutor(context=self.context)
            else:
                self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            self.context.try_shutdown()
            raise
        self._thread: Optional[threading.Thread] = None
        self.error: Optional[str] = None
        self.closed = False

    def start(self) -> "RosNode":
        if self._thread is None:
            # closed before the interpreter finalises: an executor whose thread is still running
            # then (rclpy's EventsExecutor) aborts the process ("terminate called without an
            # active exception")
            atexit.register(self.close)
            self._thread = threading.Thread(target=self._spin, name=f"ros2-{self.node.get_name()}", daemon=True)
            self._thread.start()
        return self

    def _spin(self) -> None:
        name_this_thread(f"ros2-{self.node.get_name()}")
        try:
            while self.context.ok() and not self.closed:
                self.executor.spin_once(timeout_sec=0.05)
        except Exception as e:   # the owner reads it (status, holds); the node stops spinning
            if not self.closed:
                self.error = f"{type(e).__name__}: {e}"

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        atexit.unregister(self.close)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.executor.shutdown(timeout_sec=0.5)
            self.node.destroy_node()
        finally:
            self.context.try_shutdown()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
