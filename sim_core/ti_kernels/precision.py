"""The batched CG's storage precision: which float type its stored matrices take on the device.

The batched CG (:class:`~sim_core.ti_kernels.pcg.BatchedPCG`) reads, every iteration, the operator's values (the
both-triangle CSR values, the vertex blocks ``E_t``) and its preconditioner (the vertex 3x3 inverses, the band
blocks' tiles, :class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`); its passes are bound by the bytes they read.
In ``"mixed"`` precision those arrays are stored as float32, each value rounded once from the float64 value
computed (the factorisations run in float64), and every product loads them into float64 arithmetic: the CG's
vectors, step sizes, dot products and stopping test stay float64. The CG then solves ``A~ x = b`` for ``A~`` the
operator rounded entry by entry (``|A~ - A| <= 2^-24 |A|`` entrywise), preconditioned by an approximation of the
same order to the preconditioner: for a solve stopped at a relative residual ``rtol`` far above ``2^-24``
``cond(A)``, the answer is one of the same tolerance (the standard argument for mixed-precision iterative solvers:
Higham, Accuracy and Stability of Numerical Algorithms, 2nd ed., Sec. 2.6 and 7.1; Carson & Higham, "Accelerating
the solution of linear systems by iterative refinement in three precisions", SIAM J. Sci. Comput. 40, 2018). It is
meant for the lockstep's inexact Newton solves (``rtol`` 1e-4); ``"double"`` keeps every array float64.
"""

from sim_core.errors import ConfigError
from sim_core.solver_config import CG_PRECISIONS
from sim_core.ti_backend import ti

VALUES = ti.types.ndarray(ndim=1)
"""The annotation of a stored value array of the batched CG: a 1-D ndarray of float64 or float32 (each kernel is
compiled once per dtype)."""


def storage_dtype(precision: str):
    """The Taichi dtype of the batched CG's stored matrices in ``precision`` (one of
    :data:`~sim_core.solver_config.CG_PRECISIONS`).

    Raises:
        ConfigError: an unknown precision.
    """
    if precision not in CG_PRECISIONS:
        raise ConfigError(f"batched CG precision must be one of {'|'.join(CG_PRECISIONS)}, got {precision!r}")
    return ti.f64 if precision == "double" else ti.f32


@ti.func
def stored(value, array: ti.template()):
    """``value`` cast to ``array``'s element type (rounded once where that is float32), to be stored there."""
    return ti.cast(value, array.get_type().element_type)
