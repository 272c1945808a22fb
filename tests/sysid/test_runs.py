"""``sysid.runs.segments``: the one runs-of-True rule beneath the wrench check and the signature tests."""

import numpy as np

from sysid.runs import segments


def test_segments_are_the_maximal_runs_half_open():
    mask = np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], bool)
    runs = segments(mask)
    assert runs == [(0, 2), (4, 5), (6, 9)]
    rebuilt = np.zeros_like(mask)
    for i0, i1 in runs:
        assert mask[i0:i1].all()
        assert i0 == 0 or not mask[i0 - 1]
        assert i1 == mask.size or not mask[i1]
        rebuilt[i0:i1] = True
    assert np.array_equal(rebuilt, mask)


def test_segments_of_empty_all_false_and_all_true():
    assert segments(np.zeros(0, bool)) == []
    assert segments(np.zeros(5, bool)) == []
    assert segments([1, 1, 1]) == [(0, 3)]


def test_the_signature_tests_and_the_wrench_check_take_the_same_rule():
    from sysid import wrench_check
    from sysid.diagnose.signatures import base, friction, sensor, sheet

    for module in (base, friction, sensor, sheet, wrench_check):
        assert module.segments is segments
