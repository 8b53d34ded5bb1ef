"""The run-wide cache of shared intermediates (pipeline/shared.py): declared kinds only,
content keys only, the most recent kept (one computation however many threads ask:
tests/test_pipeline.py test10b)."""
from __future__ import annotations

import numpy as np
import pytest

from dermis.pipeline.shared import RunCache, Shared

A, B = Shared("test_a"), Shared("test_b", keep=2)


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
