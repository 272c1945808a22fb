"""The lockstep line search's per-copy backtrack decided on the device (Taichi): the slope and Armijo tests of a trial
point, each copy's acceptance and halving, and the next trial point's step sizes, written where the trial point's
per-copy scalars are (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.launch_scalars`), so that the host sends
no step sizes a trial point and reads one array back: the copies' flags, their backtracks, accepted steps and energies,
the trial gradient's largest entry and the count of copies still backtracking.

The decision is the host's (:func:`sim_core.batch.line_search.armijo_accepts` and the halvings of
:meth:`~sim_core.batch.line_search.CopyLineSearch._line_search_copies`), entry by entry in the same float64 operations
and order, so the two agree bit for bit (IEEE comparisons, NaN failing every
test; ``fast_math`` is off, :func:`sim_core.ti_backend.init_backend`). Its state is one float64 array ``(ROWS B + 1,)``
in device memory, row ``r`` of copy ``c`` at ``r B + c``, the last cell the count; row :data:`ALPHA` is also the
step-size array the trial point's kernel reads (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.moved_by`).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels import device_copy, transfer
from sim_core.ti_kernels.copy_vectors import SCALARS
from sim_core.ti_kernels.launch import fast_kernel

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I64 = ti.types.ndarray(dtype=ti.i64, ndim=1)

ALPHA, E0, SLOPE, BOUND, STEP, TAKEN, ENERGY, PENDING, ACCEPTED, BACKTRACKS, LARGEST = range(11)
"""Rows of the state: the next trial's step size of each copy (``a`` where pending, plus the accepted step), the
energy at the line search's start (J), the slope ``g.d`` there, the slope test's bound ``(1 - 2 c) |g.d|``, the step
a pending copy tries, the accepted step, the energy where the copy stands (J), 1 while pending, 1 once accepted, its
halvings, and the last trial gradient's largest ``|g_k|`` (NaN where it has a NaN)."""
ROWS = 11


@fast_kernel
def _decide(scalars: _I64, with_device: ti.i32, host: _F64, with_host: ti.i32, state: _F64, copies: ti.i32,
            armijo_c: ti.f64, round_off: ti.f64):
    """One trial point's tests for every copy ``c`` (the module docstring): ``scalars`` the trial's
    :func:`~sim_core.ti_kernels.copy_vectors._scalars` output (row 0 the slope ``g.d``, rows 1 / 2 the largest
    ``|g_k|`` and its NaN flag, with ``with_device`` row ``SCALARS`` the device terms' energies), ``host`` ``(2 B,)``
    the host terms' energies and the device sums' host part (read as 0 without ``with_host``); the energy is
    ``host[c] + (device + host[B + c])``, as the host adds it."""
    state[ROWS * copies] = 0.0
    for c in range(copies):
        big = ti.bit_cast(scalars[copies + c], ti.f64)
        if scalars[2 * copies + c] > 0:
            big = ti.bit_cast(ti.i64(0x7FF8000000000000), ti.f64)
        state[LARGEST * copies + c] = big
        if state[PENDING * copies + c] > 0.0:
            s = ti.bit_cast(scalars[c], ti.f64)
            device = ti.f64(0.0)
            if with_device:
                device = ti.bit_cast(scalars[SCALARS * copies + c], ti.f64)
            first = ti.f64(0.0)
            last = ti.f64(0.0)
            if with_host:
                first = host[c]
                last = host[copies + c]
            energy = first + (device + last)
            if not with_device:
                energy = first + last
            e0 = state[E0 * copies + c]
            a = state[STEP * copies + c]
            finite = (ti.bit_cast(s, ti.i64) >> 52) & 0x7FF != 0x7FF
            ok = 0
            if finite and s <= state[BOUND * copies + c]:
                if energy - e0 <= armijo_c * a * state[SLOPE * copies + c] + round_off * ti.abs(e0):
                    ok = 1
            if ok:
                state[ENERGY * copies + c] = energy
                state[ACCEPTED * copies + c] = 1.0
                state[TAKEN * copies + c] = a
                state[PENDING * copies + c] = 0.0
            else:
                state[BACKTRACKS * copies + c] += 1.0
                state[STEP * copies + c] = a * 0.5
                ti.atomic_add(state[ROWS * copies], 1.0)
        if state[PENDING * copies + c] > 0.0:
            state[ALPHA * copies + c] = state[STEP * copies + c] + state[TAKEN * copies + c]
        else:
            state[ALPHA * copies + c] = 0.0 + state[TAKEN * copies + c]


class DeviceBacktrack:
    """The per-copy backtrack of a lockstep line search on the device (module docstring).

    Args:
        copies: ``B``.
    """

    def __init__(self, copies: int) -> None:
        self.copies = int(copies)
        size = ROWS * self.copies + 1
        self.state = device_copy.new_ndarray(ti.f64, (size,))
        self._host_state = np.zeros(size)
        self._host = device_copy.new_ndarray(ti.f64, (max(2 * self.copies, 1),))
        self._host_values = np.zeros(self._host.shape[0])

    def start(self, e0: np.ndarray, slope: np.ndarray, bound: np.ndarray, step: np.ndarray, pending: np.ndarray,
              accepted: np.ndarray, taken: np.ndarray, energy: np.ndarray, backtracks: np.ndarray) -> np.ndarray:
        """A line search's state, in one upload: per copy (each ``(B,)``) its energy ``e0`` at the start (J), slope
        ``g.d``, the slope test's bound, the step ``step`` a pending copy tries next, pending and accepted flags
        (bool), accepted steps ``taken``, ``energy`` where it stands (J) and halvings so far. Returns the next trial's
        step sizes ``(B,)`` (a new array; :data:`ALPHA`)."""
        B = self.copies
        rows = self._host_state[: ROWS * B].reshape(ROWS, B)
        rows[:] = 0.0
        rows[ALPHA] = np.where(pending, step, 0.0) + taken
        rows[E0], rows[SLOPE], rows[BOUND], rows[STEP] = e0, slope, bound, step
        rows[TAKEN], rows[ENERGY], rows[BACKTRACKS] = taken, energy, backtracks
        rows[PENDING], rows[ACCEPTED] = pending, accepted
        transfer.upload(self.state, self._host_state)
        return rows[ALPHA].copy()

    def decide(self, scalars, with_device: bool, host_energies: np.ndarray, host_sums: np.ndarray,
               armijo_c: float) -> dict:
        """One trial point's decision (:func:`_decide`) and the state read back in one copy. ``scalars``: the trial's
        scalars output on the device (with its device energies where ``with_device``); ``host_energies`` and
        ``host_sums`` ``(B,)`` (J): the host terms' energies and the device sums' host part, sent only where one is
        not zero. Returns the copies' ``pending``, ``accepted`` (bool), ``backtracks`` (int64), ``taken`` (the
        accepted steps), ``energy`` (J where each copy stands), ``largest`` (the trial gradient's largest ``|g_k|``),
        ``alpha`` (the next trial's step sizes), each ``(B,)`` a new array, and ``halved``, the copies that halved
        their step at this trial point."""
        B = self.copies
        with_host = bool(np.any(host_energies) or np.any(host_sums))
        if with_host:
            self._host_values[:B] = host_energies
            self._host_values[B: 2 * B] = host_sums
            transfer.upload(self._host, self._host_values)
        _decide(scalars, int(with_device), self._host, int(with_host), self.state, B, float(armijo_c), 1e-14)
        out = transfer.download(self.state, self._host_state)
        rows = out[: ROWS * B].reshape(ROWS, B)
        return {"pending": rows[PENDING] > 0, "accepted": rows[ACCEPTED] > 0,
                "backtracks": rows[BACKTRACKS].astype(np.int64), "taken": rows[TAKEN].copy(),
                "energy": rows[ENERGY].copy(), "largest": rows[LARGEST].copy(), "alpha": rows[ALPHA].copy(),
                "halved": int(out[ROWS * B])}
