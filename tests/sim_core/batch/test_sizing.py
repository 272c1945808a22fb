"""Batch size chosen to fit the device (sim_core.batch.sizing): the rule's edge cases, the per-copy
memory of a probe (a real resident-set measurement of known allocations), the free memory of
/proc/meminfo, and the choice over host and GPU memory."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from sim_core.batch import sizing
from sim_core.batch.sizing import (MIB, auto_batch_size, batch_size_arg, choose_batch_size, host_available_bytes,
                                   measure_per_copy, per_copy_from_probe, resources_of)
from sim_core.errors import ConfigError, InsufficientMemoryError


def test_auto_batch_size_is_the_largest_that_fits_less_the_reserve():
    assert auto_batch_size(10 * MIB, 100 * MIB, reserve_fraction=0.0) == 10
    assert auto_batch_size(10 * MIB, 100 * MIB - 1, reserve_fraction=0.0) == 9  # a byte short of the tenth copy
    assert auto_batch_size(10 * MIB, 100 * MIB, reserve_fraction=0.2) == 8
    assert auto_batch_size(10 * MIB, 100 * MIB, cap=3, reserve_fraction=0.2) == 3
    assert auto_batch_size(10 * MIB, 100 * MIB, cap=50, reserve_fraction=0.2) == 8
    assert auto_batch_size(10 * MIB, 10 * MIB, reserve_fraction=0.0) == 1  # exactly one copy
    assert auto_batch_size(1e-300, 1e300, cap=4) == 4  # no overflow


def test_auto_batch_size_errors():
    with pytest.raises(InsufficientMemoryError, match=r"not even one copy fits in GPU memory: one copy needs 10\.0 MiB"):
        auto_batch_size(10 * MIB, 12 * MIB, reserve_fraction=0.2, what="GPU")  # 9.6 MiB usable
    with pytest.raises(InsufficientMemoryError, match="0.0 MiB free"):
        auto_batch_size(1, 0)
    for per, free, cap, reserve, match in [(0, MIB, None, 0.2, "memory per copy"), (float("nan"), MIB, None, 0.2, "per copy"),
                                           (float("inf"), MIB, None, 0.2, "per copy"), (1, -1, None, 0.2, "free"),
                                           (1, MIB, 0, 0.2, "cap"), (1, MIB, None, 1.0, "reserve"),
                                           (1, MIB, None, -0.1, "reserve")]:
        with pytest.raises(ConfigError, match=match):
            auto_batch_size(per, free, cap, reserve)
    assert issubclass(InsufficientMemoryError, ConfigError)  # a CLI reports it as a usage error


def test_batch_size_arg_takes_a_positive_integer_or_auto():
    assert batch_size_arg("auto") == "auto" and batch_size_arg("4") == 4
    for bad in ("0", "-2", "four", "2.5"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"an integer >= 1 or auto, got '{bad}'"):
            batch_size_arg(bad)


def test_per_copy_from_probe_takes_the_larger_figure():
    assert per_copy_from_probe(100, 150, 200) == 50
    assert per_copy_from_probe(100, 180, 200) == 50  # the first copy carried 30 of set-up: the mean
    assert per_copy_from_probe(100, 110, 200) == 90  # the second copy's increment
    with pytest.raises(ConfigError, match="no memory growth"):
        per_copy_from_probe(100, 100, 90)


def test_measure_per_copy_of_known_allocations_on_the_host():
    """Each probe copy holds 32 MiB of touched float64 memory: the resident set grows by that per copy."""
    def build(B: int):
        return [np.ones(4 * MIB) for _ in range(B)]  # 4 Mi float64 = 32 MiB, pages touched

    per = measure_per_copy(build, ("host",))
    assert per["host"] == pytest.approx(32 * MIB, rel=0.1)


def test_measure_per_copy_skips_resources_it_cannot_read():
    calls = iter(range(100))
    per = measure_per_copy(lambda B: B, ("host", "gpu"),
                           used=lambda r: 5.0 * MIB * next(calls) if r == "host" else None)
    assert set(per) == {"host"} and per["host"] == pytest.approx(5 * MIB)  # readings 0, 5, 10 MiB


def test_choose_batch_size_takes_the_tightest_resource():
    free = {"host": 1000 * MIB, "gpu": 100 * MIB}.get
    got = choose_batch_size({"host": 5 * MIB, "gpu": 1 * MIB}, reserve_fraction=0.0, free=free)
    assert (got.B, got.limit) == (100, "gpu")
    got = choose_batch_size({"host": 20 * MIB, "gpu": 1 * MIB}, reserve_fraction=0.0, free=free)
    assert (got.B, got.limit) == (50, "host")
    got = choose_batch_size({"host": 20 * MIB, "gpu": 1 * MIB}, cap=7, reserve_fraction=0.0, free=free)
    assert (got.B, got.limit) == (7, "cap")
    rec = got.as_record()
    assert rec["auto_B"] == 7 and rec["gpu_mib_per_copy_probe"] == 1.0 and rec["host_mib_free"] == 1000.0
    with pytest.raises(InsufficientMemoryError, match="GPU"):
        choose_batch_size({"host": 1 * MIB, "gpu": 200 * MIB}, free=free)
    with pytest.raises(ConfigError, match="could be read"):
        choose_batch_size({"host": 1 * MIB}, free=lambda r: None)
    assert choose_batch_size({"host": 1 * MIB}, cap=3, free=lambda r: None).B == 3


def test_free_and_used_memory_of_the_host(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       16000000 kB\nMemFree:  100 kB\nMemAvailable:    2048 kB\n")
    assert host_available_bytes(meminfo) == 2 * MIB
    meminfo.write_text("MemTotal:       16000000 kB\n")
    assert host_available_bytes(meminfo) is None
    assert host_available_bytes(tmp_path / "missing") is None
    assert sizing.free_memory("host") > 0 and sizing.used_memory("host") > 0  # this Linux machine
    assert resources_of("taichi-cuda") == ("host", "gpu") and resources_of("numpy") == ("host",)


def test_measure_per_copy_traces_the_heap_when_the_resident_set_does_not_grow():
    """Memory the allocator reuses does not grow the resident set; the traced heap still counts it."""
    def build(B: int):
        return [np.ones(MIB) for _ in range(B)]  # 8 MiB a copy

    per = measure_per_copy(build, ("host",), used=lambda r: 100.0 * MIB)  # a flat resident set
    assert per["host"] == pytest.approx(8 * MIB, rel=0.05)
    with pytest.raises(ConfigError, match="no host memory growth"):
        measure_per_copy(lambda B: None, ("host",), used=lambda r: 100.0 * MIB)


def test_a_gpu_that_does_not_grow_is_left_out():
    """Copies that fit in a memory pool the GPU already holds: the host sizes the batch."""
    host = iter([10 * MIB, 20 * MIB, 30 * MIB])
    per = measure_per_copy(lambda B: B, ("host", "gpu"),
                           used=lambda r: next(host) if r == "host" else 500.0 * MIB)
    assert per == {"host": pytest.approx(10 * MIB)}
