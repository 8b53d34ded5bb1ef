"""The run-wide cache of shared intermediates (pipeline/shared.py): declared kinds only,
content keys only, one computation however many threads ask."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dermis.pipeline.shared import RunCache, Shared

A, B = Shared("test_a"), Shared("test_b", keep=2)


def test_concurrent_askers_share_one_computation():
    cache, calls, out = RunCache(), [], []

    def make():
        calls.append(1)
        time.sleep(0.05)           # long enough for every thread to ask while it runs
        return object()

    threads = [threading.Thread(target=lambda: out.append(cache.get_made(A, ("k", 1), make)))
               for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len({id(v) for v, _ in out}) == 1
    assert sorted(m for _, m in out) == [False] * 7 + [True]


def test_a_node_gets_only_the_kinds_it_declares():
    run = RunCache()
    view = run.restricted((A,))
    assert view.get(A, "x", lambda: 3) == 3
    with pytest.raises(LookupError, match="test_b"):
        view.get(B, "x", lambda: 4)
    # the views share one store: another node declaring A finds the value made above
    assert run.restricted((A, B)).get(A, "x", lambda: 5) == 3


@pytest.mark.parametrize("key", [object(), np.zeros(3), ("a", [1, 2]), {"a": 1}])
def test_keys_are_plain_content(key):
    with pytest.raises(TypeError):
        RunCache().get(A, key, lambda: 0)


def test_keep_holds_the_most_recently_used():
    cache, made = RunCache(), []
    for k in ("p", "q", "p", "r", "p", "q"):
        cache.get(B, k, lambda k=k: made.append(k) or k)
    # keep=2: q is dropped when r comes (p was used after q), then made again
    assert made == ["p", "q", "r", "q"]
