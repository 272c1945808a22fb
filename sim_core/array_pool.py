"""Large host arrays handed out again once nothing else holds them, instead of fresh ones at every call.

A contact set's candidate search makes arrays of every candidate pair (1.8 million pairs at 1024 stacked Forming
copies: the sorted pairs, their vertices, 20-45 MB each) that live until a later search replaces them. A fresh array
of that size is fresh memory: its pages are faulted in (and zeroed by the kernel) when first written, which on the
2-core VM took 40-100 ms for 43 MB while other large arrays were alive, against 2-5 ms for writing into memory
already touched (docs/benchmarks_log.md, session 45, 28search3; session 46, 28search4). :class:`ArrayPool` keeps the
blocks it handed out and hands a block out again only when the pool's own reference is the only one left (CPython's
reference count: no caller, view or cache still holds it), so a reused block can never be read by an earlier holder;
where every block is still held, a new one is made. The values are those of a fresh array written the same way.
"""

from __future__ import annotations

import sys

import numpy as np


class ArrayPool:
    """Blocks of arrays by name, reused when unreferenced (module docstring).

    Args:
        keep: the most blocks kept per name; beyond it the pool forgets its oldest block (which lives on while
            its holders hold it).
    """

    def __init__(self, keep: int = 3) -> None:
        if keep < 1:
            raise ValueError(f"ArrayPool: keep must be >= 1, got {keep}")
        self.keep = keep
        self._blocks: dict[str, list[np.ndarray]] = {}

    def empty(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """An uninitialised C-contiguous array of ``shape`` and ``dtype``: the first ``shape[0]`` rows of a kept block
        ``name`` of at least as many rows, the same trailing shape and dtype that nothing else holds, else of a new
        block (an eighth longer, for the next call's growth).

        Args:
            name: the kind of array (blocks of one name are handed out for one use).
            shape: at least one dimension.
            dtype: a NumPy dtype.

        Raises:
            ValueError: an empty ``shape``.
        """
        shape = tuple(int(n) for n in shape)
        if not shape:
            raise ValueError("ArrayPool.empty: shape must have at least one dimension")
        dtype = np.dtype(dtype)
        blocks = self._blocks.setdefault(name, [])
        for i in range(len(blocks)):
            # the list's reference and getrefcount's argument: no other holder (caller, view or cache)
            if sys.getrefcount(blocks[i]) == 2 and blocks[i].dtype == dtype and blocks[i].shape[1:] == shape[1:]:
                if blocks[i].shape[0] >= shape[0]:
                    return blocks[i][:shape[0]]
                del blocks[i]  # too short and unused: made again below at the size asked for
                break
        block = np.empty((shape[0] + shape[0] // 8,) + shape[1:], dtype=dtype)
        blocks.append(block)
        if len(blocks) > self.keep:
            del blocks[0]
        return block[:shape[0]]

    def copy_of(self, name: str, values: np.ndarray, dtype=None) -> np.ndarray:
        """:meth:`empty` of ``values``' shape holding ``values`` converted to ``dtype`` (``values``' own by default;
        converted as ``astype`` does): a pooled ``values.astype(dtype)``.

        Raises:
            ValueError: a 0-dimensional ``values``.
        """
        out = self.empty(name, values.shape, values.dtype if dtype is None else dtype)
        np.copyto(out, values, casting="unsafe")
        return out
