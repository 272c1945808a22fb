"""Cheaper launches of compiled Taichi kernels: argument handling cached per call signature.

A ``@ti.kernel`` call in Taichi 1.7 spends most of its time in Python before the compiled code
runs: it re-derives the template key from every argument (``TaichiCallableTemplateMapper``),
walks the annotations (``recursive_set_args``) and checks each NumPy array's size, about 75 us
per call for the 7 to 9 array arguments of the fused and contact kernels, against about 30 us for
the launch itself (2-core VM). A Newton step of the Forming scene makes ~50 such calls.

:func:`fast_kernel` wraps a kernel so that the first call of each *call signature* (per argument:
the dtype and rank of a NumPy array or of a Taichi ndarray, the type of a scalar, the value of a
template argument) goes
through Taichi's own path, which compiles, validates and launches; it then records the compiled
kernel and a plan of typed argument setters, and later calls with that signature fill the launch
context directly (``set_arg_external_array_with_shape`` / ``set_arg_ndarray`` / ``set_arg_float`` /
``set_arg_int``, the calls Taichi's ``Kernel.launch_kernel`` makes) and launch the same compiled code.
A Taichi ndarray argument (device memory on CUDA: the kernels of one environment keep their arrays
there) then costs no more Python than a NumPy one, against about 45-75 us a call through Taichi's
path on the H200 host (``benchmarks/profile_single.py``). On the CPU
the plan keeps its launch context and sets again only the array arguments that are other array
objects than at the last launch and the scalars that changed (:class:`_Plan`; constant index and
rest-shape arrays are bound once), which cuts a launch with 7 arrays from about 60 us to 15 us. A
call is tried first on the last call's plan, checking each argument against that plan's signature
as it is set (about 4 us of Python for the 14 arguments of the contact batch kernel, against 12 to
19 us when the signature was built and looked up at every call). The results are those of the
plain call: same compiled kernel, same argument values.

Anything the plan does not cover takes Taichi's path every time: keyword arguments, arrays that
are neither C-contiguous NumPy arrays nor Taichi scalar ndarrays without a gradient, ndarray
annotations with a matrix/vector element type, struct, matrix or argpack arguments, kernels that
print or return anything but one scalar, and any call after the Taichi program was re-initialised
(the plans of the old program are dropped).
"""

from __future__ import annotations

import ctypes
import functools
import threading
from typing import Any, Callable

import numpy as np
from taichi.lang._ndarray import ScalarNdarray as _ScalarNdarray
from taichi.lang.util import cook_dtype
from taichi.types import ndarray_type, primitive_types, template
from taichi.types.utils import is_signed

from sim_core.ti_backend import ti  # first: Taichi through ti_backend, which silences its import banner
from sim_core.ti_kernels import device_copy

_runtime = ti.lang.impl.get_runtime  # (taichi is imported through ti_backend, which silences its banner)

_ARRAY, _FLOAT, _INT, _UINT, _TEMPLATE = range(5)
_NDARRAY = "ndarray"  # the first entry of a Taichi ndarray argument's signature: (_NDARRAY, dtype, ndim)


def _argument_kinds(primal) -> list[int] | None:
    """Setter kind of each kernel argument, or None if some argument is not covered."""
    kinds = []
    for argument in primal.arguments:
        anno = argument.annotation
        if isinstance(anno, template):
            kinds.append(_TEMPLATE)
        elif isinstance(anno, ndarray_type.NdarrayType):
            if not (anno.dtype is None or id(anno.dtype) in primitive_types.type_ids):
                return None
            kinds.append(_ARRAY)
        elif id(anno) in primitive_types.real_type_ids:
            kinds.append(_FLOAT)
        elif id(anno) in primitive_types.integer_type_ids:
            kinds.append(_INT if is_signed(cook_dtype(anno)) else _UINT)
        else:
            return None
    return kinds


def _return_getter(primal) -> Callable | None | bool:
    """``None`` (no return value), a getter of the one scalar returned, or False (not covered)."""
    ret = primal.return_type
    if ret is None:
        return None
    if len(ret) != 1:
        return False
    (dtype,) = ret
    if dtype in primitive_types.real_types:
        return lambda ctx: ctx.get_struct_ret_float((0,))
    if dtype in primitive_types.integer_types:
        if is_signed(cook_dtype(dtype)):
            return lambda ctx: ctx.get_struct_ret_int((0,))
        return lambda ctx: ctx.get_struct_ret_uint((0,))
    return False


_MISMATCH = object()  # what :meth:`_Plan.launch` returns for arguments of another signature


class _Plan:
    """A compiled kernel and its argument setters for one call signature.

    On the CPU the plan also keeps one launch context and, per argument slot, what was last set in
    it: Taichi's CPU launcher only copies a bound host array's pointer into the kernel's argument
    buffer at each launch (``cpu::KernelLauncher::launch_llvm_kernel``), so a slot that gets the same
    NumPy array object again (same buffer, shape, strides and dtype) needs no new
    ``set_arg_external_array_with_shape``, which is most of a launch's Python cost (about 4 us per
    array), and a scalar slot that gets the same value again (a float other than zero, whose sign
    the comparison would not see) needs no new ``set_arg_*``. Other archs copy external arrays to the
    device per launch, and calls from another thread than the one that made the context (a fit's
    worker thread beside a node's) could interleave their bindings, so those get a new context each
    call.

    Args:
        t_kernel: Taichi's compiled-kernel handle of the signature.
        slots: per non-template argument ``(argument position, launch index, kind, expected)``,
            ``expected`` being ``(dtype number, ndim)`` for an array and the Python type otherwise.
        templates: per template argument ``(position, type, value)``.
        ret: the getter of the returned scalar, or None.
    """

    __slots__ = ("t_kernel", "slots", "templates", "ret", "compiled", "ctx", "bound", "thread")

    def __init__(self, t_kernel, slots: list[tuple[int, int, int, Any]], templates: list[tuple[int, type, Any]],
                 ret: Callable | None) -> None:
        self.t_kernel = t_kernel
        self.slots = slots
        self.templates = templates
        self.ret = ret
        self.compiled = None  # the compiled kernel data (the program's cache entry), set on first launch
        self.ctx = None  # the reused launch context (CPU only)
        self.bound: list = [None] * len(slots)  # per slot: what ctx holds (see _bind)
        self.thread: int | None = None  # the thread that owns ctx

    def launch(self, runtime, args: tuple, checked: bool) -> Any:
        """Set ``args`` in the launch context and launch; returns the kernel's result, or
        :data:`_MISMATCH` (nothing launched) when ``args`` (not ``checked`` against this plan's
        signature) are of another signature."""
        if not checked:
            for position, value_type, value in self.templates:
                v = args[position]
                if type(v) is not value_type or v != value:
                    return _MISMATCH
        prog = runtime.prog
        compiled = self.compiled
        if compiled is None:
            compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), self.t_kernel)
            self.compiled = compiled
            if _host_arch(runtime):
                self.ctx = self.t_kernel.make_launch_context()
                self.thread = threading.get_ident()
        ctx = self.ctx
        bound = self.bound
        if ctx is None or self.thread != threading.get_ident():
            ctx = self.t_kernel.make_launch_context()
            bound = None
        for n, (position, index, kind, expected) in enumerate(self.slots):
            v = args[position]
            last = None if bound is None else bound[n]
            if kind == _ARRAY:
                if expected[0] is _NDARRAY:  # a Taichi ndarray: bound by its allocation, as Taichi's own call does,
                    # at every launch (a launch replaces the allocation it was given with its address)
                    if not checked and (type(v) is not _ScalarNdarray or v.grad is not None
                                        or v.dtype != expected[1] or len(v.shape) != expected[2]):
                        return _MISMATCH
                    ctx.set_arg_ndarray((index,), v.arr)
                    continue
                if last is not None and last[0] is v and last[1] == v.shape and last[2] is v.dtype \
                        and last[3] == v.strides:
                    continue
                if not checked and (type(v) is not np.ndarray or not v.flags.c_contiguous
                                    or (v.dtype.num, v.ndim) != expected):
                    return _MISMATCH
                if bound is not None:
                    bound[n] = (v, v.shape, v.dtype, v.strides)
                ctx.set_arg_external_array_with_shape((index,), _data_pointer(v), v.nbytes, v.shape, 0)
                continue
            if not checked and type(v) is not expected:
                return _MISMATCH
            if last is not None and last[0] == v and (kind != _FLOAT or v != 0.0):
                continue
            if kind == _FLOAT:
                ctx.set_arg_float((index,), float(v))
            elif kind == _INT:
                ctx.set_arg_int((index,), int(v))
            else:
                ctx.set_arg_uint((index,), int(v))
            if bound is not None:
                bound[n] = (v,)
        prog.launch_kernel(compiled, ctx)
        if self.ret is None:
            return None
        # Taichi's own call syncs through the runtime, which also materialises new fields: not
        # needed for a kernel compiled before them (any later call through Taichi's path does it)
        prog.synchronize()
        return self.ret(ctx)


class FastKernel:
    """A Taichi kernel whose repeated calls skip Taichi's per-call argument analysis (module docstring).

    A call is first tried on the plan of the last call (its argument checks folded into the
    binding of the arguments); arguments of another signature look their plan up by signature.

    Args:
        kernel: a function decorated with ``@ti.kernel`` (not a class kernel).

    Raises:
        TypeError: ``kernel`` is not a Taichi kernel.
    """

    def __init__(self, kernel: Callable) -> None:
        if not getattr(kernel, "_is_wrapped_kernel", False) or getattr(kernel, "_is_classkernel", False):
            raise TypeError(f"FastKernel: {kernel!r} is not a plain @ti.kernel function")
        functools.update_wrapper(self, kernel)
        self.kernel = kernel
        self._primal = kernel._primal
        self._kinds = _argument_kinds(self._primal)
        self._plans: dict[tuple, _Plan | None] = {}
        self._last_plan: _Plan | None = None
        self._prog = None

    def _signature(self, args: tuple) -> tuple | None:
        kinds = self._kinds
        if kinds is None or len(args) != len(kinds):
            return None
        key = []
        for arg, kind in zip(args, kinds):
            if kind == _ARRAY:
                if type(arg) is _ScalarNdarray:
                    if arg.grad is not None:
                        return None
                    key.append((_NDARRAY, arg.dtype, len(arg.shape)))
                    continue
                if type(arg) is not np.ndarray or not arg.flags.c_contiguous:
                    return None
                key.append((arg.dtype.num, arg.ndim))
            elif kind == _TEMPLATE:
                if not isinstance(arg, (bool, int, float, str)):
                    return None
                key.append((type(arg), arg))
            else:
                key.append(type(arg))
        return tuple(key)

    def _make_plan(self, args: tuple, signature: tuple) -> _Plan | None:
        """The plan of ``args``' ``signature``, built after Taichi's own call compiled and ran it."""
        primal = self._primal
        ret = _return_getter(primal)
        if ret is False or primal.has_print:
            return None
        t_kernel = primal.compiled_kernels[primal.ensure_compiled(*args)]
        slots, templates, index = [], [], 0
        for position, kind in enumerate(self._kinds):
            if kind == _TEMPLATE:
                templates.append((position, *signature[position]))
            else:
                slots.append((position, index, kind, signature[position]))
                index += 1
        return _Plan(t_kernel, slots, templates, ret)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        runtime = _runtime()
        if runtime.prog is not self._prog:
            self._plans.clear()
            self._last_plan = None
            self._prog = runtime.prog
        plan = self._last_plan
        if plan is not None and not kwargs and len(args) == len(self._kinds):
            result = plan.launch(runtime, args, checked=False)
            if result is not _MISMATCH:
                return result
        signature = None if kwargs else self._signature(args)
        plan = self._plans.get(signature) if signature is not None else None
        if plan is None:
            result = self.kernel(*args, **kwargs)
            if signature is not None and signature not in self._plans:
                self._plans[signature] = self._make_plan(args, signature)
            return result
        self._last_plan = plan
        return plan.launch(runtime, args, checked=True)


def _data_pointer(array: np.ndarray) -> int:
    """Address of the first element of a C-contiguous ``array`` (``array.ctypes.data``, which builds a
    ctypes helper object, ~3 us; through the buffer protocol ~0.8 us where the array is writable and
    not empty)."""
    if array.nbytes and array.flags.writeable:  # from_buffer refuses a read-only buffer
        return ctypes.addressof(ctypes.c_char.from_buffer(array))
    return array.ctypes.data


def _host_arch(runtime) -> bool:
    """Whether the Taichi program runs on the host CPU (x64 / arm64), where launch contexts are reused."""
    return runtime.prog.config().arch in (ti.x64, ti.arm64)


def fast_kernel(fn: Callable) -> FastKernel:
    """``@fast_kernel`` in place of ``@ti.kernel``: a Taichi kernel with cached launch plans (module docstring)."""
    return FastKernel(ti.kernel(fn))


SUM_CELLS = 1024
"""Cells of a :func:`summing_kernel`'s sum array on a GPU (on the CPU: one). A kernel adds element ``k``'s term into
cell ``k % cells``, so that its parallel loop's atomic additions spread over this many addresses instead of
serialising on one: Taichi 1.7 keeps a loop's sum into a field in per-thread registers (``make_thread_local``) but
not a sum into an ndarray element, which is one global atomic addition per element (about a million a fused
evaluation at 1024 stacked Forming copies)."""


def summing_kernel(fn: Callable) -> Callable[..., float]:
    """``@summing_kernel`` in place of ``@fast_kernel`` for a kernel that sums a scalar over its loops
    (an energy in J): the kernel's last argument is a float64 array ``energy`` of cells, zeroed before each launch,
    into which it adds element ``k``'s term at cell ``k % energy.shape[0]`` (:data:`SUM_CELLS` cells on a GPU, one
    on the CPU: ``energy[0] += ...``); the returned function takes the other arguments, launches the kernel (a
    :func:`fast_kernel`) with an array kept per thread, and returns the sum of the cells (in cell order).

    Why not a returned scalar (``-> ti.f64``) summed in a local variable: on CUDA such a kernel's parallel
    loop took 1.9 ms whatever its element count (210 to 1,125 elements, energy alone or with the
    Hessian, Taichi 1.7.4 on an H200: docs/benchmarks_log.md, session 38, 28single), about 40 ms a
    Forming step, where a sum into an array element takes microseconds. On the CPU (serial loops, one cell) the
    additions are the same, in the same order: the same sum bit for bit. On a GPU the array is a Taichi
    ndarray in device memory, zeroed by the driver's memset and copied back by
    :func:`sim_core.ti_kernels.device_copy.to_host` (a NumPy argument would make Taichi's launcher copy it to the
    device and back and synchronise).
    """
    kernel = fast_kernel(fn)
    cells = threading.local()

    @functools.wraps(fn)
    def summed(*args: Any) -> float:
        deferred = getattr(_DEFERRED, "active", None)
        if deferred is not None:  # launched into a cell of the block's own, read after the block
            kernel(*args, deferred._next_cell())
            return float("nan")
        runtime = _runtime()
        if getattr(cells, "prog", None) is not runtime.prog:  # (a device array belongs to one Taichi program)
            cells.array, cells.prog = _new_cells(runtime), runtime.prog
        _zero_cells(cells.array)
        kernel(*args, cells.array)
        return _cells_sum(cells.array)

    summed.kernel = kernel  # the FastKernel itself
    return summed


def element_cells(summed: Callable, count: int, *args: Any):
    """``summed`` (a :func:`summing_kernel` function) launched on ``args`` with a zeroed sum array of ``count`` cells,
    so that element ``k < count`` adds its term into cell ``k`` alone (:data:`SUM_CELLS`'s rule ``k % cells``; for a
    kernel whose loops number their elements ``0 .. count - 1``). Returns the cells: float64 ``(count,)``, a NumPy
    array on the host arch, else a Taichi ndarray in device memory kept per thread and size (valid until the next
    call for that size). :func:`~sim_core.ti_kernels.copy_vectors.copy_energies` sums them by copy where they are."""
    runtime = _runtime()
    if _host_arch(runtime):
        cells = np.zeros(max(count, 1))
        if count > 0:
            summed.kernel(*args, cells)
        return cells[:count]
    kept = getattr(_ELEMENT_CELLS, "arrays", None)
    if kept is None or kept[0] is not runtime.prog:  # (a device array belongs to one Taichi program)
        kept = _ELEMENT_CELLS.arrays = (runtime.prog, {})
    array = kept[1].get(count)
    if array is None:
        array = kept[1][count] = device_copy.new_ndarray(ti.f64, (max(count, 1),))
    _zero_cells(array)
    if count > 0:
        summed.kernel(*args, array)
    return array


_ELEMENT_CELLS = threading.local()
"""Per thread: ``arrays``, ``(Taichi program, {count: device array})`` of :func:`element_cells` on a GPU."""


def _new_cells(runtime):
    """A sum array of a :func:`summing_kernel`: ``(1,)`` NumPy on the host arch, a ``(SUM_CELLS,)`` Taichi ndarray
    in device memory on a GPU."""
    return np.zeros(1) if _host_arch(runtime) else device_copy.new_ndarray(ti.f64, (SUM_CELLS,))


def _zero_cells(array) -> None:
    """Set the cells of ``array`` (:func:`_new_cells`) to zero (on a GPU by the driver's memset: no kernel launch,
    ordered after the launches before it)."""
    if isinstance(array, np.ndarray):
        array.fill(0.0)
    elif not device_copy.zero(array):
        array.fill(0.0)


def _cells_sum(array) -> float:
    """The sum of the cells of ``array`` (:func:`_new_cells`), in cell order (on a GPU: read after the kernels
    launched before, by the driver's copy)."""
    if isinstance(array, np.ndarray):
        return float(array[0]) if array.size == 1 else float(np.sum(array))
    host = np.empty(tuple(array.shape))
    if not device_copy.to_host(host, array):
        host = array.to_numpy()
    return float(np.sum(host))


_DEFERRED = threading.local()
"""Per thread: ``active``, the :class:`DeferredSums` whose block is running, or None."""


class DeferredSums:
    """A block in which the calling thread's :func:`summing_kernel` launches do not wait for their sums.

    Within ``with DeferredSums() as sums:`` each summing kernel is launched with a sum array of its own (zeroed,
    kept by this object across blocks: ``(SUM_CELLS,)`` in device memory on a GPU, ``(1,)`` on the CPU) and returns
    NaN at once, so that on a GPU the host launches the next kernel while the device runs this one, instead of
    copying each sum back (a synchronisation) before the next launch. After the block, :meth:`values` reads the
    sums in launch order (the first read waits for the kernels). The sums are those of the plain calls: same
    kernels, same arguments, each into a zeroed cell of its own.

    With ``shared`` on a GPU (sum arrays of :data:`SUM_CELLS` cells) every launch of a block adds into one sum array
    instead, zeroed once, and :meth:`total` reads the block's sum in one copy back: one zero fill and one copy a block
    instead of one of each a launch; the sum is then the terms' in another order (on a GPU the order of a
    parallel loop's atomic additions is not fixed anyway). On the CPU (one cell) each launch keeps its own cell.

    Args:
        shared: share one sum array among a block's launches where the arrays have several cells.

    Raises:
        RuntimeError: a block entered while another one is active on the same thread.
    """

    def __init__(self, shared: bool = False) -> None:
        self._cells: list = []
        self._used = 0
        self._prog = None
        self.shared = shared

    def __enter__(self) -> "DeferredSums":
        if getattr(_DEFERRED, "active", None) is not None:
            raise RuntimeError("DeferredSums: a block is already active on this thread")
        runtime = _runtime()
        if self._prog is not runtime.prog:  # (a device cell belongs to one Taichi program)
            self._cells, self._prog = [], runtime.prog
        self._used = 0
        _DEFERRED.active = self
        return self

    def __exit__(self, *exc: object) -> None:
        _DEFERRED.active = None

    @property
    def launches(self) -> int:
        """Summing-kernel launches in the current (or last) block."""
        return self._used

    @property
    def sharing(self) -> bool:
        """Whether the launches of a block add into one sum array (``shared`` where the arrays have several cells)."""
        if not self.shared:
            return False
        if not self._cells:
            self._cells.append(_new_cells(_runtime()))
        return int(np.prod(self._cells[0].shape)) > 1

    def _next_cell(self):
        if self._used and self.sharing:  # (zeroed at the block's first launch)
            self._used += 1
            return self._cells[0]
        if self._used == len(self._cells):
            self._cells.append(_new_cells(_runtime()))
        cell = self._cells[self._used]
        _zero_cells(cell)
        self._used += 1
        return cell

    def sum_of(self, items, run, start: float = 0.0, read: bool = True):
        """``start`` plus ``run(item)`` of every item of ``items``, added in order, their summing kernels launched in
        one block of these sums (on a GPU the launches follow one another without waiting for each sum; with
        :attr:`sharing` every launch adds into one sum array, read after the block in one copy: ``start`` plus that
        sum, plus the values of the items that launched nothing). An item's ``run`` returns its kernel's sum (NaN
        inside the block, then read) or its own value (no kernel launched, e.g. no elements). ``read`` False: a
        callable returning that sum instead (its read then), valid until the next block of these sums.

        Raises:
            RuntimeError: an item launched more than one summing kernel.
        """
        returned = []  # per item: (True, index of its launch) or (False, the value it returned)
        with self:
            for item in items:
                before = self._used
                value = run(item)
                launched = self._used - before
                if launched > 1:
                    raise RuntimeError(f"DeferredSums: {type(item).__name__} launched {launched} summing kernels")
                returned.append((True, before) if launched else (False, value))

        def total() -> float:
            if self.sharing:  # (a GPU) the launched items' sums in one sum array, read in one copy
                out = start + self.total()
                for launched, item in returned:
                    out += 0.0 if launched else item
                return out
            values = self.values()
            out = start
            for launched, item in returned:
                out += values[item] if launched else item
            return out

        return total() if read else total

    def values(self) -> list[float]:
        """The sums (J) of the last block's launches, in launch order.

        Raises:
            RuntimeError: the launches shared one sum array (:attr:`sharing`: read :meth:`total`).
        """
        if self._used > 1 and self.sharing:
            raise RuntimeError("DeferredSums: the launches shared one sum array; read total()")
        return [_cells_sum(cell) for cell in self._cells[: self._used]]

    def total(self) -> float:
        """The sum (J) of the last block's launches: with :attr:`sharing`, the one sum array's cells added in cell
        order (one copy back); else the sums of :meth:`values` added in launch order (0.0 without a launch)."""
        if not self._used:
            return 0.0
        if self.sharing:
            return _cells_sum(self._cells[0])
        total = 0.0
        for value in self.values():
            total += value
        return total
