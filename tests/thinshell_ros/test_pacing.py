"""RealtimePacer: the wall-clock schedule of the sim node's realtime mode (no ROS)."""

from __future__ import annotations

import pytest

from thinshell_ros.pacing import RealtimePacer


def _steps_taken(pacer: RealtimePacer, ticks: list[float]) -> list[int]:
    """At each wall time in ``ticks``, take every due step; the count taken at each."""
    counts = []
    for now in ticks:
        n = 0
        while pacer.due(now):
            pacer.stepped()
            n += 1
        counts.append(n)
    return counts


def test_a_late_tick_takes_the_steps_it_missed():
    pacer = RealtimePacer(dt=0.005, max_lag=0.05)
    # ticks at 0, 5 ms, then the process is descheduled until 17 ms (steps due at 10 and 15 ms)
    assert _steps_taken(pacer, [0.0, 0.005, 0.017, 0.019, 0.020]) == [1, 1, 2, 0, 1]


def test_sim_time_keeps_wall_time_when_steps_average_below_dt():
    """Steps alternately 8 ms and 1 ms long (4.5 ms on average, dt 5 ms): a step starts when its
    predecessor ends if it is due, else at its due time; simulated time then stays within one step
    of wall time over 1000 steps (a timer that skips missed periods would lose 3 ms every two steps)."""
    pacer = RealtimePacer(dt=0.005, max_lag=0.05)
    now, steps = 0.0, 0
    for k in range(1000):
        while not pacer.due(now):
            now += 1e-4
        pacer.stepped()
        steps += 1
        now += 0.008 if k % 2 == 0 else 0.001
    assert abs(steps * 0.005 - now) < 0.005 + 1e-9
    assert pacer.dropped == 0.0


def test_a_lag_beyond_max_lag_is_dropped_not_caught_up():
    pacer = RealtimePacer(dt=0.005, max_lag=0.02)
    assert pacer.due(0.0)
    pacer.stepped()
    # stalled for 100 ms: the schedule restarts at 0.1 s, one step due, not twenty
    assert _steps_taken(pacer, [0.1]) == [1]
    assert pacer.dropped == pytest.approx(0.095)
    assert _steps_taken(pacer, [0.104, 0.1051]) == [0, 1]


def test_a_command_may_start_a_step_at_most_one_dt_early():
    pacer = RealtimePacer(dt=0.005, max_lag=0.05)
    assert pacer.due(0.0)
    pacer.stepped()  # step 0 at 0 ms; step 1 due at 5 ms
    assert not pacer.due(0.001) and pacer.may_start(0.001)
    pacer.stepped()  # step 1 started at 1 ms; step 2 due at 10 ms
    assert not pacer.may_start(0.002)  # a second command waits: never two steps ahead
    assert pacer.may_start(0.005) and not pacer.due(0.005)


def test_restart_begins_a_new_schedule_at_the_next_query():
    pacer = RealtimePacer(dt=0.005, max_lag=0.05)
    assert pacer.due(0.0)
    pacer.stepped()
    pacer.restart()
    assert pacer.due(0.040) and pacer.dropped == 0.0  # after a pause: no lag to drop


@pytest.mark.parametrize("dt, max_lag, match", [(0.0, 0.05, "dt must be"), (float("nan"), 0.05, "dt must be"),
                                                (0.005, -1.0, "max_lag must be")])
def test_invalid_settings_are_rejected(dt, max_lag, match):
    with pytest.raises(ValueError, match=match):
        RealtimePacer(dt=dt, max_lag=max_lag)
