"""Shared fixtures of the Taichi kernel tests: one Taichi runtime per test process, on the CPU
unless ``THINSHELL_TEST_ARCH=cuda`` asks for the GPU (on a machine with one; tests that compare
with the CPU's serial sums bit for bit then differ by round-off, by design)."""

from __future__ import annotations

import os

import numpy as np
import pytest

TEST_ARCH = os.environ.get("THINSHELL_TEST_ARCH", "cpu")


@pytest.fixture(scope="session")
def ti_cpu() -> str:
    """Initialise Taichi (float64, offline cache on) once, on ``TEST_ARCH`` (default the CPU);
    returns the arch."""
    from sim_core.ti_backend import init_backend

    return init_backend(TEST_ARCH)


def assert_same_sums(actual, expected, rel: float = 1e-12) -> None:
    """``actual`` equals ``expected`` (arrays or scalars): bit for bit on the CPU, where the kernels' loops are
    serial (the same additions in the same order); on CUDA to ``rel`` of ``expected``'s largest magnitude,
    because there the loops run in parallel and add into shared entries with atomics in an order that varies
    from launch to launch, and the compiler fuses multiply-adds (one rounding where the CPU rounds twice),
    so the last bits differ (observed on an H200: 1.4e-17 m in positions of 0.02 m, 2 ulp in energies)."""
    if TEST_ARCH == "cpu":
        np.testing.assert_array_equal(actual, expected)
    else:
        assert relative_error(np.asarray(actual, dtype=float), np.asarray(expected, dtype=float)) <= rel


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    """max|a - b| / max|b| (the whole array's scale)."""
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def assert_same_potential(ref, tik, x: np.ndarray, tol: float = 1e-10) -> None:
    """Energy, gradient and the Hessian blocks of every projection agree to ``tol`` relative."""
    e_ref, e_ti = ref.energy(x), tik.energy(x)
    assert abs(e_ti - e_ref) <= tol * abs(e_ref)
    assert relative_error(tik.gradient(x), ref.gradient(x)) < tol
    for projection in ("none", "clamp", "abs"):
        h_ref, h_ti = ref.hessian(x, projection), tik.hessian(x, projection)
        assert np.array_equal(h_ti.vertices, h_ref.vertices)
        assert h_ti.blocks.shape == h_ref.blocks.shape
        assert relative_error(h_ti.blocks, h_ref.blocks) < tol, projection


def assert_projection_active_and_psd(ref, tik, x: np.ndarray) -> None:
    """The exact blocks have clearly negative eigenvalues; Taichi's clamped blocks have none."""
    w_exact = np.linalg.eigvalsh(ref.hessian(x, "none").blocks)
    scale = np.max(np.abs(w_exact))
    assert w_exact.min() < -1e-3 * scale  # the projection has work to do at this configuration
    w = np.linalg.eigvalsh(tik.hessian(x, "clamp").blocks)
    assert w.min() >= -1e-12 * scale
    w_abs = np.linalg.eigvalsh(tik.hessian(x, "abs").blocks)
    assert w_abs.min() >= -1e-12 * scale
    assert w_abs.max() >= 0.999 * np.max(np.abs(w_exact))  # |w| keeps the magnitude of flipped modes
