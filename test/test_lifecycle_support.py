"""Managed (lifecycle) nodes are possible here: rclpy's lifecycle support and lifecycle_msgs install with
the rest of the ROS wheels, and a LifecycleNode goes unconfigured -> inactive -> active through its
~/change_state service, as a managed can_driver would."""

from __future__ import annotations

import time
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn  # noqa: E402


class _Managed(LifecycleNode):
    def __init__(self, context: Any) -> None:
        super().__init__("managed_probe", context=context)
        self.calls: list[str] = []

    def on_configure(self, state: Any) -> TransitionCallbackReturn:
        self.calls.append("configure")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: Any) -> TransitionCallbackReturn:
        self.calls.append("activate")
        return super().on_activate(state)


def test_lifecycle_node_driven_through_its_services(rclpy_context: Any) -> None:
    node = _Managed(rclpy_context)
    client = rclpy.create_node("lifecycle_client", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(client)

    def call(cli: Any, req: Any) -> Any:
        fut = cli.call_async(req)
        deadline = time.monotonic() + 10.0
        while not fut.done() and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert fut.done(), f"no answer from {cli.srv_name}"
        return fut.result()

    try:
        change = client.create_client(ChangeState, "/managed_probe/change_state")
        get = client.create_client(GetState, "/managed_probe/get_state")
        assert change.wait_for_service(timeout_sec=10.0)
        assert call(get, GetState.Request()).current_state.id == State.PRIMARY_STATE_UNCONFIGURED
        for t in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
            assert call(change, ChangeState.Request(transition=Transition(id=t))).success
        assert call(get, GetState.Request()).current_state.id == State.PRIMARY_STATE_ACTIVE
        assert node.calls == ["configure", "activate"]
    finally:
        ex.shutdown()
        client.destroy_node()
        node.destroy_node()
