"""A ROS context for a test: its own rclpy context on the test's domain, a node, and an executor
spinning on a thread of its own, so the test body only waits (this module imports rclpy)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, TypeVar

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from redarm_ros.testing.waits import DEFAULT_PERIOD_S, wait_until

N = TypeVar("N", bound=Node)

SPIN_S = 0.02  # executor wait per turn: bounds how long close() waits for the spin thread


class RosTestContext:
    """An initialised rclpy context on ``domain_id`` with a node (``node``, named ``name``) whose
    callbacks run on a background executor thread; add your own nodes with :meth:`add_node`.

    Use as a context manager or call :meth:`close`: nodes destroyed, the context shut down.
    """

    def __init__(self, domain_id: int, name: str = "redarm_test") -> None:
        self.domain_id = int(domain_id)
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self._nodes: list[Node] = []
        self.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="redarm-test-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # spin_once in a loop: spin_until_future_complete adds tens of ms per call here
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=SPIN_S)

    def add_node(self, node: N) -> N:
        """Let the executor run ``node``'s callbacks (it must use this ``context``); returns it."""
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def wait_until(self, cond: Callable[[], Any], timeout: float, *, what: str = "condition",
                   seen: Callable[[], object] | None = None) -> Any:
        """:func:`redarm_ros.testing.wait_until` (callbacks keep running meanwhile)."""
        return wait_until(cond, timeout, what=what, seen=seen, period=DEFAULT_PERIOD_S)

    def call(self, client: Any, request: Any, timeout: float = 10.0) -> Any:
        """Call a service and wait for its answer (the request is sent again while unanswered, as
        the package's own clients do).

        Raises:
            WaitTimeoutError: the service did not appear or answer within ``timeout`` s.
        """
        from redarm_ros.nodes._common import call_resending
        from redarm_ros.procs import poll_until

        name = client.srv_name
        wait_until(client.service_is_ready, timeout, what=f"service {name} available")
        answer = call_resending(client, request, lambda cond, t: poll_until(cond, t, DEFAULT_PERIOD_S),
                                timeout)
        if answer is None:
            wait_until(lambda: False, 0.0, what=f"an answer of {name} within {timeout:g} s")
        return answer

    def close(self) -> None:
        """Stop the executor thread, destroy the nodes, shut the context down."""
        self._stop.set()
        self._thread.join(10.0)
        for node in reversed(self._nodes):
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        if self.context.ok():
            rclpy.shutdown(context=self.context)

    def __enter__(self) -> RosTestContext:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

