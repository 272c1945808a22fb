"""Memoised Taichi source positions: the same messages as Taichi's, errors still located."""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np
import pytest


def _context():
    from taichi.lang.ast import ast_transformer_utils

    return ast_transformer_utils.ASTTransformerContext


def test_installed_by_init_backend_and_idempotent(ti_cpu):
    from sim_core.ti_frontend import memoize_source_positions

    installed = _context().get_pos_info
    assert hasattr(installed, "__wrapped__")  # init_backend installed it
    assert memoize_source_positions() is True
    assert _context().get_pos_info is installed  # not wrapped twice


def test_memoized_messages_equal_taichis(ti_cpu, monkeypatch):
    from sim_core.ti_backend import ti

    memoized = _context().get_pos_info
    original = memoized.__wrapped__
    seen: list[tuple[str, str]] = []

    def compare(self, node):
        message = memoized(self, node)
        seen.append((message, original(self, node)))
        return message

    monkeypatch.setattr(_context(), "get_pos_info", compare)

    @ti.func
    def scaled(v, s):
        return ti.Vector([v[0] * s,
                          v[1] * s, v[2] * s])  # a node over two lines

    @ti.kernel
    def frontend_probe(a: ti.types.ndarray(dtype=ti.f64, ndim=2), out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        for i in range(a.shape[0]):
            v = ti.Vector([a[i, 0], a[i, 1], a[i, 2]])
            acc = 0.0
            for k in ti.static(range(3)):  # the ti.func inlined three times: repeated positions
                if v[k] > 0.0:
                    acc += scaled(v, 1.0 + k).sum()
            out[i] = acc

    a = np.array([[1.0, -2.0, 3.0], [0.5, 0.25, -1.0]])
    out = np.zeros(2)
    frontend_probe(a, out)
    assert np.allclose(out, [(1.0 - 2.0 + 3.0) * (1.0 + 3.0), (0.5 + 0.25 - 1.0) * (1.0 + 2.0)])
    assert len(seen) > 50
    messages = [m for m, _ in seen]
    assert len(set(messages)) < len(messages)  # repeated positions were served from the memo
    assert all(m == o for m, o in seen)
    assert any("a node over two lines" in m for m in messages)  # multi-line nodes quote every line


def test_compile_error_still_names_file_line_and_source(ti_cpu):
    from sim_core.ti_backend import ti

    @ti.kernel
    def broken_probe(out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        for i in range(out.shape[0]):
            out[i] = undefined_name_of_the_probe  # noqa: F821

    lines = open(__file__).read().splitlines()
    expected = next(k for k, text in enumerate(lines, 1) if "= undefined_name_of_the_probe" in text)
    with pytest.raises(Exception, match="undefined_name_of_the_probe") as err:
        broken_probe(np.zeros(1))
    message = str(err.value)
    assert f'test_ti_frontend.py", line {expected}, in broken_probe' in message
    assert "out[i] = undefined_name_of_the_probe" in message and "^^^" in message


def test_memoized_function_sources_equal_inspects(ti_cpu):
    from taichi.lang import kernel_impl

    from sim_core.energies.hinge_bending import kernel as bending
    from sim_core.ti_frontend import memoize_function_sources

    assert memoize_function_sources() is True  # installed by init_backend; idempotent
    lines_of, file_of = kernel_impl.getsourcelines, kernel_impl.getsourcefile
    assert hasattr(lines_of, "__wrapped__") and hasattr(file_of, "__wrapped__")
    fn = bending._theta_hessian.func.func  # the Python function of a ti.func (decorated -> Func -> function)
    first, again = lines_of(fn), lines_of(fn)
    assert first == lines_of.__wrapped__(fn) and again == first
    assert first[0] is not again[0]  # a fresh list each time (the caller may change it)
    assert first[0][1].lstrip().startswith("def _theta_hessian(")
    assert file_of(fn) == file_of.__wrapped__(fn) == bending.__file__
