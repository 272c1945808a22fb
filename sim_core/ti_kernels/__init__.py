"""Taichi infrastructure shared by the energies' kernels (``sim_core/energies/<energy>/*kernel.py``).

``buffers`` (device arrays filled once per shape), ``launch`` (cached kernel launches), ``linalg``
(small dense eigen-decomposition and PSD projection in ``ti.func``), ``block_projection`` (PSD
projection of element blocks into CSR slots), and the broad phase of the contact candidates
(``broad_phase`` sort-and-sweep, ``hash_grid`` spatial hash, ``sweep_candidates`` /
``hash_candidates`` with ``pair_filters``). This package's ``__init__`` does not import Taichi.
"""
