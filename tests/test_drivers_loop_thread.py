"""The stoppable background loop behind every driver's and simulated twin's thread."""
import threading
import time

from collect.loop_thread import LoopThread
from conftest import wait_until


def counting_loop():
    """A LoopThread whose loop counts its passes (one per 1 ms) and records its thread's name."""
    passes = []
    names = []

    def loop():
        names.append(threading.current_thread().name)
        while not thread.stop_event.wait(0.001):
            passes.append(1)

    thread = LoopThread(loop, "test-loop")
    return thread, passes, names


def test_runs_until_stopped_then_stays_stopped():
    thread, passes, names = counting_loop()
    assert not thread.running
    thread.start()
    assert thread.running
    assert wait_until(lambda: len(passes) >= 3)
    thread.stop()
    assert not thread.running
    stopped_at = len(passes)
    time.sleep(0.02)
    assert len(passes) == stopped_at  # joined: the loop has returned
    assert names == ["test-loop"]


def test_start_while_running_starts_no_second_loop():
    thread, _, names = counting_loop()
    thread.start()
    thread.start()
    assert wait_until(lambda: len(names) >= 1)
    time.sleep(0.01)
    thread.stop()
    assert names == ["test-loop"]


def test_restarts_after_stop_and_stop_is_safe_to_repeat():
    thread, passes, names = counting_loop()
    thread.stop()  # never started
    thread.start()
    thread.stop()
    thread.stop()
    before = len(passes)
    thread.start()  # the stop request of the first run is cleared
    assert wait_until(lambda: len(passes) >= before + 3)
    thread.stop()
    assert names == ["test-loop", "test-loop"]


def test_stop_gives_up_on_a_loop_that_ignores_it():
    release, returned = threading.Event(), threading.Event()

    def stuck():
        release.wait(30.0)  # ignores its stop until the test releases it
        returned.set()

    thread = LoopThread(stuck, "stuck-loop", join_timeout_s=0.05)
    thread.start()
    started = time.monotonic()
    thread.stop()
    waited = time.monotonic() - started
    gave_up = not returned.is_set()  # stop() came back while the loop was still blocked
    release.set()
    assert gave_up
    assert waited >= 0.04  # after waiting join_timeout_s (0.05 s) for it: a lower bound, which load only lengthens
    assert not thread.running
