"""The positions key of the terms' kept evaluations (sim_core.energies.base.positions_key): arrays over memory of
another owner given to ``FrozenPositionsKey.register`` (the lockstep solver's trial points in page-locked blocks) are
keyed by identity, the same arrays unregistered or writeable by their bytes, and a registration ends with its array."""

from __future__ import annotations

import ctypes
import gc

import numpy as np
import pytest

from sim_core.energies.base import FrozenPositionsKey, positions_key


def _over_buffer(values: np.ndarray) -> np.ndarray:
    """A writeable float64 copy of ``values`` over a ctypes buffer (an array whose base is another owner's)."""
    buffer = (ctypes.c_byte * values.nbytes)()
    out = np.ndarray(values.shape, dtype=np.float64, buffer=buffer)
    out[:] = values
    return out


def test_registered_arrays_are_keyed_by_identity_and_others_by_their_bytes():
    x = np.random.default_rng(3).normal(size=(40, 3))
    registered, plain = _over_buffer(x), _over_buffer(x)
    assert positions_key(registered) == positions_key(x)  # writeable, over a buffer: its bytes
    assert FrozenPositionsKey.register(registered) is registered and not registered.flags.writeable
    plain.flags.writeable = False  # read-only but not registered: its base's owner may still write it
    assert FrozenPositionsKey.holds(registered) and not FrozenPositionsKey.holds(plain)
    assert positions_key(registered) == positions_key(registered) != positions_key(x)
    assert positions_key(plain) == positions_key(x) != positions_key(registered)
    view = registered[:]  # a view of a registered array: another object, keyed by its bytes
    assert not FrozenPositionsKey.holds(view) and positions_key(view) == positions_key(x)
    own = x.copy()
    own.flags.writeable = False  # owns its memory: frozen without registration, as before
    assert FrozenPositionsKey.holds(own) and positions_key(own) != positions_key(x.copy())


def test_a_registration_ends_with_its_array():
    x = np.arange(12.0).reshape(4, 3)
    a = FrozenPositionsKey.register(_over_buffer(x))
    ident = id(a)
    assert ident in FrozenPositionsKey._registered
    del a
    gc.collect()
    assert ident not in FrozenPositionsKey._registered
    b = _over_buffer(x)  # a new array, perhaps at the same id: not registered
    b.flags.writeable = False
    assert not FrozenPositionsKey.holds(b) and positions_key(b) == positions_key(x)


def test_register_refuses_what_is_not_a_float64_array():
    with pytest.raises(ValueError, match="float64 np.ndarray"):
        FrozenPositionsKey.register(np.zeros((2, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="float64 np.ndarray"):
        FrozenPositionsKey.register([[0.0, 0.0, 0.0]])
