"""One rclpy node with its own context, spun by an executor in its own thread.

Every ROS 2 part of pointfence (a camera source's bridge, a camera node, a CRTK arm's bridge,
the telemetry) owns one ``RosNode``: its callbacks run on the node's thread, never on the 1 kHz
haptic loop's, and they hand data over through the owner's own buffers. A context of its own
per node lets several nodes live in one process and be shut down independently (tests).

The 1 kHz topics of the bridges' own periodic loops (a CRTK arm's measured_cp and measured_js,
a master's pose, gripper and pedal, the simulators' commands and forces) are
``PolledSubscription``s instead: no executor serves them, the loop takes
what arrived once a period. On the executor every message woke its thread as well as the
middleware's, a second thread hand-off (and interpreter-lock handover) per message that cost a
third of such a process's CPU time at 1 kHz on two cores.
"""
from __future__ import annotations

import atexit
import threading
import time
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
        self._polled_node = None
        self.error: Optional[str] = None
        self.closed = False

    def polled(self, msg_type, topic: str, qos) -> "PolledSubscription":
        """A raw subscription to ``topic`` that no executor serves (``PolledSubscription``); it
        lives on a second node of this context, which is never spun."""
        if self._polled_node is None:
            rclpy = dds.rclpy()
            self._polled_node = rclpy.create_node(self.node.get_name() + "_polled", namespace=self.node.get_namespace(),
                                                  context=self.context)
        return PolledSubscription(self._polled_node, msg_type, topic, qos)

    def start(self) -> "RosNode":
        if self._thread is None:
            # closed before the interpreter finalises: an executor whose thread is still running
            # then (rclpy's EventsExecutor) aborts the process ("terminate called without an
            # active exception")
            atexit.register(self.close)
            self._thread = threading.Thread(target=self._spin, name=f"ros2-{self.node.get_name()}", daemon=True)
            self._thread.start()
        return self

    @property
    def thread(self) -> Optional[threading.Thread]:
        """The thread the executor spins on (None before ``start()``)."""
        return self._thread

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
            if self._polled_node is not None:
                self._polled_node.destroy_node()
        finally:
            self.context.try_shutdown()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()


def _never(_msg) -> None:        # (the callback of a subscription no executor serves)
    raise AssertionError("a polled subscription's callback ran: its node was added to an executor")


class PolledSubscription:
    """A raw subscription whose owner takes the messages itself, in its own thread, when it wants
    them: ``take()`` gives the oldest waiting message as (its bytes, its arrival on
    ``time.monotonic()``, s) or None when none waits. The arrival is the middleware's reception
    time (``received_timestamp``, on the wall clock, mapped onto the monotonic one), so a message
    that waited for its taker reads as old as it is. The quality of service's history depth bounds
    how many messages wait; older ones are dropped by the middleware."""

    def __init__(self, node, msg_type, topic: str, qos):
        self.topic = topic
        self._type = msg_type
        self._sub = node.create_subscription(msg_type, topic, _never, qos, raw=True)
        # rclpy's own executors and ``rclpy.wait_for_message`` take messages this way
        self._take = self._sub.handle.take_message

    def take_all(self):
        """Every waiting message, oldest first, as ``take`` gives them (a generator)."""
        got = self.take()
        while got is not None:
            yield got
            got = self.take()

    def take(self) -> Optional[tuple]:
        got = self._take(self._type, True)
        if got is None:
            return None
        raw, info = got
        received = int(info.get("received_timestamp") or 0)
        if received <= 0:      # (a middleware that does not stamp receptions: the take is the arrival)
            return raw, time.monotonic()
        age = (time.time_ns() - received) * 1e-9
        return raw, time.monotonic() - max(0.0, age)
