"""call_resending: a request whose answer never comes is sent again, and the first answer to any copy
is taken (Fast DDS drops a response when the server has not matched the caller's reply reader yet)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import SimpleNamespace

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.callback_groups import ReentrantCallbackGroup  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.task import Future  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from redarm_ros.nodes import _common  # noqa: E402
from redarm_ros.nodes._common import call_resending  # noqa: E402
from redarm_ros.procs import poll_until  # noqa: E402


class FakeClient:
    """call_async hands out futures; ``answer_copy`` (1-based) gets answered at once, the rest never."""

    def __init__(self, answer_copy: int | None) -> None:
        self.answer_copy = answer_copy
        self.futures: list[Future] = []
        self.removed: list[Future] = []

    def call_async(self, request: object) -> Future:
        fut = Future()
        self.futures.append(fut)
        if len(self.futures) == self.answer_copy:
            fut.set_result(f"answer to copy {len(self.futures)}")
        return fut

    def remove_pending_request(self, fut: Future) -> None:
        self.removed.append(fut)


def test_an_unanswered_request_is_sent_again_and_the_answer_taken() -> None:
    cli = FakeClient(answer_copy=3)
    resends: list[int] = []
    resp = call_resending(cli, object(), poll_until, timeout=5.0, resend_after_s=0.05,
                          on_resend=resends.append)
    assert resp == "answer to copy 3"
    assert resends == [1, 2]  # the first and second extra copy
    assert cli.removed == cli.futures[:2]  # the abandoned copies no longer wait for an answer


def test_no_answer_at_all_gives_none_after_the_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    # On a clock that moves only while call_resending waits: the count of copies does not depend on how
    # soon a loaded machine wakes the waiting thread.
    clock = [0.0]
    monkeypatch.setattr(_common, "time", SimpleNamespace(monotonic=lambda: clock[0]))

    def wait(pred: Callable[[], bool], seconds: float) -> bool:
        clock[0] += seconds
        return pred()

    cli = FakeClient(answer_copy=None)
    assert call_resending(cli, object(), wait, timeout=0.3, resend_after_s=0.1) is None
    assert len(cli.futures) == 3  # sent at 0, 0.1 and 0.2 s
    assert cli.removed == cli.futures


def test_an_answered_first_request_is_not_sent_again() -> None:
    cli = FakeClient(answer_copy=1)
    assert call_resending(cli, object(), poll_until, timeout=5.0, resend_after_s=0.05) == "answer to copy 1"
    assert len(cli.futures) == 1 and cli.removed == []


def test_a_real_service_whose_first_answer_never_comes(rclpy_context: Context) -> None:
    """Through rclpy: the server holds its first request until the end of the test (as good as a lost
    response for the caller); the copy sent after ``resend_after_s`` is answered."""
    release = threading.Event()
    calls: list[int] = []

    def on_request(_req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        calls.append(len(calls) + 1)
        if len(calls) == 1:
            release.wait(10.0)
        resp.success, resp.message = True, f"request {len(calls)}"
        return resp

    ctx = rclpy_context
    server = rclpy.create_node("resend_server", context=ctx)
    server.create_service(Trigger, "resend_probe", on_request, callback_group=ReentrantCallbackGroup())
    caller = rclpy.create_node("resend_caller", context=ctx)
    cli = caller.create_client(Trigger, "resend_probe")
    ex = MultiThreadedExecutor(num_threads=3, context=ctx)
    ex.add_node(server)
    ex.add_node(caller)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        assert cli.wait_for_service(timeout_sec=10.0)
        resp = call_resending(cli, Trigger.Request(), poll_until, timeout=20.0, resend_after_s=0.5)
        assert resp is not None and resp.success and resp.message == "request 2"
        assert calls == [1, 2]
    finally:
        release.set()
        ex.shutdown(timeout_sec=5.0)
        spin.join(5.0)
        server.destroy_node()
        caller.destroy_node()
