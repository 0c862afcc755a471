"""The one cache policy: least recently used out first, within a byte budget."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from analysis.cache import Cache, nbytes_of
from analysis.pipeline.stages import STAGE_COST, StageClock


def test_least_recently_used_goes_first_within_the_budget():
    cache = Cache(max_bytes=3000)
    a, b, c = (np.zeros(125) for _ in range(3))  # 1000 bytes each
    cache.put("a", a)
    cache.put("b", b)
    cache.put("c", c)
    assert cache.nbytes == 3000 and len(cache) == 3
    assert cache.get("a") is a                  # now the most recently used
    cache.put("d", np.zeros(125))
    assert "b" not in cache and "a" in cache and "c" in cache and "d" in cache
    assert cache.nbytes == 3000


def test_an_entry_larger_than_the_budget_is_returned_but_not_kept():
    cache = Cache(max_bytes=100)
    big = cache.get_or_make("big", lambda: np.zeros(1000))
    assert big.shape == (1000,) and "big" not in cache and cache.nbytes == 0


def test_get_or_make_makes_once():
    cache = Cache()
    calls = []
    for _ in range(3):
        cache.get_or_make(("kind", "owner", 1), lambda: calls.append(1) or np.ones(3))
    assert len(calls) == 1


def test_take_removes_and_put_returns():
    cache = Cache()
    buf = cache.put(("refocus", "t", "acc"), np.zeros(10))
    assert cache.take(("refocus", "t", "acc")) is buf and cache.take(("refocus", "t", "acc")) is None
    assert cache.nbytes == 0


def test_entries_of_one_kind_and_owner():
    cache = Cache()
    cache.put(("normalisation", "t1", b"x"), np.zeros(2))
    cache.put(("normalisation", "t2", b"x"), np.zeros(2))
    cache.put(("refocus", "t1", "x"), np.zeros(2))
    assert [k for k, _ in cache.entries("normalisation", "t1")] == [("normalisation", "t1", b"x")]


def test_sizes_of_nested_values():
    class Holder:
        nbytes = 7
    assert nbytes_of((np.zeros(2), [np.zeros(1), Holder()], {"a": np.zeros(1)})) == 16 + 8 + 7 + 8
    assert nbytes_of("text") == 0


def test_budget_holds_under_threads():
    cache = Cache(max_bytes=50 * 800)

    def work(k: int) -> None:
        for i in range(200):
            cache.put((k, i), np.zeros(100))
            cache.get((k, i - 3))

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert cache.nbytes == 800 * len(cache) <= cache.max_bytes


def test_negative_budget_is_refused():
    with pytest.raises(ValueError):
        Cache(max_bytes=-1)


def test_stage_clock_reports_weighted_progress_and_times():
    seen = []
    clock = StageClock(lambda fraction, stage: seen.append((fraction, stage)))
    with clock.stage("refocus"):
        pass
    with clock.stage("refine"):
        pass
    timings = clock.finish()
    assert [s for _, s in seen] == ["refocus", "refine", "done"]
    total = sum(STAGE_COST.values())
    assert seen[1][0] == pytest.approx(STAGE_COST["refocus"] / total)  # by cost, not by count
    assert seen[-1][0] == 1.0 and set(timings) == {"refocus", "refine", "total"}
