"""The Newton loop evaluates the pair contacts with derivatives at a line search's first trial point
(``_PairPenalty.keep_derivatives``): the next iterate's gradient and Hessian then need no kernel
launch of their own, and the steps are the same bit for bit."""

from __future__ import annotations

import numpy as np


def _forming(steps: int, monkeypatch, prefetch: bool) -> tuple[np.ndarray, list[int], list[tuple]]:
    """Final positions (m), Newton iterations per step and the batch kernel's launches
    ``(derivatives, pairs)`` of ``steps`` Forming benchmark steps on the Taichi path."""
    from sim_core.energies.contact import batch_kernel as contact_batch
    from sim_core.energies.contact.reference import _PairPenalty
    from tests.support.forming import forming_simulation, step_benchmark_trajectory

    with monkeypatch.context() as patch:
        if not prefetch:
            patch.setattr(_PairPenalty, "keep_derivatives", lambda self, x: None)
        calls = []
        kernel = contact_batch._batch_kernel
        patch.setattr(contact_batch, "_batch_kernel", lambda *a: (calls.append((a[7], len(a[3]))), kernel(*a)))
        sim = forming_simulation()
        iterations = step_benchmark_trajectory(sim, steps)
        return sim.state.x.copy(), iterations, calls


def test_contact_derivatives_prefetched_at_the_trial_point_same_steps_fewer_launches(ti_cpu, monkeypatch):
    x_ref, it_ref, calls_ref = _forming(8, monkeypatch, prefetch=False)
    x, it, calls = _forming(8, monkeypatch, prefetch=True)
    np.testing.assert_array_equal(x, x_ref)
    assert it == it_ref
    # without the prefetch an accepted trial point is evaluated twice: its values (line search), then
    # the derivatives of its active pairs (the next iterate's gradient); with it, once (Forming, 8
    # steps: 91 -> 60 launches)
    assert sum(1 for derivatives, _ in calls_ref if derivatives) > len(calls_ref) / 3
    assert len(calls) <= len(calls_ref) - (sum(it) - 2 * len(it))
    assert len(calls) < 0.75 * len(calls_ref)
