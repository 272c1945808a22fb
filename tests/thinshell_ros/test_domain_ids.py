"""The per-test ROS domain ids of tests/thinshell_ros/conftest.py: disjoint between xdist workers, in 1..101."""

from __future__ import annotations

import pytest

from tests.thinshell_ros.conftest import _domain_id


@pytest.mark.parametrize("n", [1, 2, 3, 8])
def test_workers_never_share_a_domain_and_ids_stay_in_the_safe_range(n):
    ids = {w: {_domain_id(f"gw{w}", str(n), k) for k in range(1000)} for w in range(n)}
    for w in range(n):
        assert min(ids[w]) >= 1 and max(ids[w]) <= 101
        assert len(ids[w]) == 101 // n                      # consecutive tests of a worker cycle through its share
        for v in range(w):
            assert not ids[w] & ids[v]
    # consecutive tests of one worker get different domains
    assert _domain_id("gw1", "2", 7) != _domain_id("gw1", "2", 8)


def test_bad_worker_names_and_counts_are_refused():
    with pytest.raises(ValueError, match="gw<int>"):
        _domain_id("master", "2", 0)
    with pytest.raises(ValueError, match="at most 101"):
        _domain_id("gw0", "102", 0)
