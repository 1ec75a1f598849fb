"""The correction's per-pair thread map (``pipeline/registration/parallel.py``): results in the items' order,
the calls spread over more than one thread, an error raised to the caller."""

import threading
import time

import pytest
from tandemscan.pipeline.registration.parallel import pair_threads


def test_pair_map_keeps_the_order_of_the_items_whatever_order_they_finish_in():
    def slow_for_small(x: int) -> int:
        time.sleep(0.002 * (10 - x))  # the first items finish last
        return x * x

    with pair_threads() as pair_map:
        assert pair_map(slow_for_small, range(10)) == [x * x for x in range(10)]


def test_pair_map_runs_items_on_several_threads(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    both_running = threading.Barrier(2, timeout=5)

    def meet(_: int) -> str:
        both_running.wait()  # only returns when a second thread is in here at the same time
        return threading.current_thread().name

    with pair_threads() as pair_map:
        names = pair_map(meet, range(2))
    assert len(set(names)) == 2


def test_pair_map_raises_an_items_error():
    def fail_on_three(x: int) -> int:
        if x == 3:
            raise ValueError("pair 3")
        return x

    with pair_threads() as pair_map, pytest.raises(ValueError, match="pair 3"):
        pair_map(fail_on_three, range(6))
