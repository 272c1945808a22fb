"""The displacements since a candidate search, bounded per body segment, where the positions are (Taichi).

:meth:`sim_core.contact_set.ContactSet.covers` asks whether the candidate lists searched at ``x_search`` still
hold every close pair at an iterate ``x``: from the displacements ``u = x - x_search`` it needs the largest
``|u|`` over all vertices and, per body segment (a run of vertices) and axis, the largest and smallest ``u``.
:class:`DisplacementBounds` computes these where a Taichi ndarray of ``x`` is (device memory on CUDA: the
lockstep batch's iterates) and reads back one small array (segments + 1 rows of 7 numbers) instead of
reading every position on the host. Two launches, every array argument in device memory on CUDA (the chunk and
segment tables are sent once, with :func:`~sim_core.ti_kernels.buffers.on_device`: a NumPy argument of a CUDA launch
is copied to the device and back, and waited for, at each launch): per chunk of at most :data:`CHUNK` vertices of
one segment, its bounds (:func:`_chunk_bounds`); per segment, those of its chunks (:func:`_segment_bounds`). Maxima and
minima are exact (no rounding, any order), and ``u`` is the host's ``x - x_search`` entry by entry, so the
bounds equal the host's ``np.maximum.reduceat`` / ``np.minimum.reduceat`` bit for bit where they are finite; a
NaN or infinite ``u`` is flagged per segment (and overall) and read as NaN (``covers`` then answers as the host
does: no list covers such a segment).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import on_device
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.transfer import download, upload

_F64_2, _I32_1 = linalg.F64_2, linalg.I32_1

CHUNK = 256
"""Vertices a thread of :func:`_chunk_bounds` reads."""

_HIGH, _LOW, _LARGEST, _NAN = 0, 3, 6, 7  # columns of a chunk's row


@fast_kernel
def _chunk_bounds(x: _F64_2, x_search: _F64_2, chunk_start: _I32_1, bounds: _F64_2):
    """Row ``c`` of ``bounds`` ``(chunks, 8)``, of vertices ``chunk_start[c] <= v < chunk_start[c + 1]``, with
    ``u = x[v] - x_search[v]``: ``[max u (3), min u (3), max |u|, 1 if some u is NaN or infinite else 0]``
    (the test on the bits: the compiler's fast math may drop ``u != u``)."""
    for c in range(chunk_start.shape[0] - 1):
        high = ti.Vector([-ti.math.inf, -ti.math.inf, -ti.math.inf], ti.f64)
        low = ti.Vector([ti.math.inf, ti.math.inf, ti.math.inf], ti.f64)
        largest = ti.f64(0.0)
        nan = ti.f64(0.0)
        for v in range(chunk_start[c], chunk_start[c + 1]):
            for k in ti.static(range(3)):
                u = x[v, k] - x_search[v, k]
                if (ti.bit_cast(u, ti.i64) >> 52) & 0x7FF == 0x7FF:  # all exponent bits: NaN or infinite
                    nan = 1.0
                else:
                    high[k] = ti.max(high[k], u)
                    low[k] = ti.min(low[k], u)
                    largest = ti.max(largest, ti.abs(u))
        for k in ti.static(range(3)):
            bounds[c, _HIGH + k] = high[k]
            bounds[c, _LOW + k] = low[k]
        bounds[c, _LARGEST] = largest
        bounds[c, _NAN] = nan


@fast_kernel
def _segment_bounds(bounds: _F64_2, first_chunk: _I32_1, stop_chunk: _I32_1, out: _F64_2):
    """Row ``s`` of ``out`` ``(r, 8)``: the bounds of chunks ``first_chunk[s] <= c < stop_chunk[s]`` (a segment's;
    the last row every chunk's)."""
    for s in range(first_chunk.shape[0]):
        high = ti.Vector([-ti.math.inf, -ti.math.inf, -ti.math.inf], ti.f64)
        low = ti.Vector([ti.math.inf, ti.math.inf, ti.math.inf], ti.f64)
        largest = ti.f64(0.0)
        nan = ti.f64(0.0)
        for c in range(first_chunk[s], stop_chunk[s]):
            for k in ti.static(range(3)):
                high[k] = ti.max(high[k], bounds[c, _HIGH + k])
                low[k] = ti.min(low[k], bounds[c, _LOW + k])
            largest = ti.max(largest, bounds[c, _LARGEST])
            nan = ti.max(nan, bounds[c, _NAN])
        for k in ti.static(range(3)):
            out[s, _HIGH + k] = high[k]
            out[s, _LOW + k] = low[k]
        out[s, _LARGEST] = largest
        out[s, _NAN] = nan


class DisplacementBounds:
    """Bounds of the displacements ``u = x - x_search`` (m) of ``n`` vertices split into body segments.

    Args:
        n: vertices (rows of the positions).
        segment_starts: first vertex of each segment, increasing, int ``(s,)``; segment ``i`` runs to the next
            start (the last to ``n``); vertices before the first start belong to none (they count in the largest
            ``|u|`` only).

    Raises:
        ValueError: starts that are not increasing or not in ``[0, n)``.
    """

    def __init__(self, n: int, segment_starts: np.ndarray) -> None:
        starts = np.asarray(segment_starts, dtype=np.int64)
        if len(starts) and (np.any(np.diff(starts) <= 0) or starts[0] < 0 or starts[-1] >= n):
            raise ValueError(f"DisplacementBounds: segment starts must increase within [0, {n}); got {starts}")
        self.n = int(n)
        edges = np.concatenate([[0], starts, [n]])
        runs = [np.arange(a, b, CHUNK) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        chunk_start = np.concatenate(runs + [[n]]).astype(np.int32)
        # the first chunk of each segment (chunks never cross a segment's start), then the chunk count
        segment_chunk = np.searchsorted(chunk_start, np.concatenate([starts, [n]]))
        chunks = len(chunk_start) - 1
        self.segments = len(starts)
        self._chunk_start = chunk_start
        # the rows of _segment_bounds: each segment's chunks, then every chunk
        self._first_chunk = np.append(segment_chunk[:-1], 0).astype(np.int32)
        self._stop_chunk = np.append(segment_chunk[1:], chunks).astype(np.int32)
        self._chunk_bounds = new_ndarray(ti.f64, (chunks, 8))
        self._out = new_ndarray(ti.f64, (self.segments + 1, 8))
        self._host = np.empty((self.segments + 1, 8))
        self._search = None  # (x_search, its ndarray) of the last upload
        self._device: dict = {}  # on CUDA: the device copies of the chunk and segment tables (buffers.on_device)

    def __call__(self, x_search: np.ndarray, x_device, kept: bool) -> tuple[np.ndarray, np.ndarray, float]:
        """``(high, low, largest)``: per segment and axis the largest and smallest ``u`` ``(s, 3)`` (m; NaN in a
        segment where some ``u`` is NaN or infinite) and the largest ``|u|`` over every vertex (NaN if some ``u`` is).

        Args:
            x_search: the search positions ``(n, 3)`` (m), sent to the device unless they are the last call's
                ``kept`` array (an array whose values cannot change: a frozen one).
            x_device: the positions ``x`` as a float64 Taichi ndarray ``(n, 3)`` (m).
            kept: whether ``x_search`` may be kept by identity.

        Raises:
            ValueError: ``x_device`` or ``x_search`` not of shape ``(n, 3)``.
        """
        if tuple(x_device.shape) != (self.n, 3) or x_search.shape != (self.n, 3):
            raise ValueError(f"DisplacementBounds: positions must be ({self.n}, 3); got {tuple(x_device.shape)} "
                             f"and {x_search.shape}")
        search = self._search
        if search is None or search[0] is not x_search or not kept:
            array = search[1] if search is not None else new_ndarray(ti.f64, (self.n, 3))
            upload(array, x_search)
            search = self._search = (x_search if kept else None, array)
        dev = self._device
        _chunk_bounds(x_device, search[1], on_device(dev, "chunk_start", self._chunk_start), self._chunk_bounds)
        _segment_bounds(self._chunk_bounds, on_device(dev, "first_chunk", self._first_chunk),
                        on_device(dev, "stop_chunk", self._stop_chunk), self._out)
        out = download(self._out, self._host)
        segments = out[:-1]
        nan = segments[:, _NAN] > 0.0
        high, low = segments[:, _HIGH:_HIGH + 3].copy(), segments[:, _LOW:_LOW + 3].copy()
        high[nan], low[nan] = np.nan, np.nan
        largest = float("nan") if out[-1, _NAN] > 0.0 else float(out[-1, _LARGEST])
        return high, low, largest
