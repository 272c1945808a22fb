"""The calibration's first secant replay in a second process, beside the calibration's start replay.

A diagnosis's calibration (:func:`sysid.calibration.calibrate`) replays the recording three times, one
after the other: the start replay at the scene values (the parameter fit's first and, with the
default budget of one replay, only point), then the secant stage's probe at a third of the stick
regularisation and its Gauss-Newton step (:mod:`sysid.calibration_secant`). When the fit takes no
step, the probe's parameters are known before the start replay begins: the scene values with
``contact.eps_v`` scaled (:func:`sysid.calibration_secant.first_probe_values`). A
:class:`ProbeWorker` makes that replay in a forked process while this one makes the start replay;
the secant stage takes it where its parameters are bitwise the ones it would replay
(:func:`~sysid.calibration_secant.secant_calibration` ``first``), else replays them itself. A replay
is a deterministic function of its parameters (the simulation is reset before each, solver caches
included: :meth:`sim_core.simulation.Simulation.reset`), so the calibration makes the same replays
and reaches the same values as in one process; on two cores its wall time falls by about one replay.

The child is forked before this process starts Taichi (Taichi's runtime does not survive ``fork``,
:mod:`sysid.diagnose.parallel`); it starts its own. It sends back the replay without its states and
the later replays' start (:func:`~sysid.calibration_secant.resume_before_contact`).

After the probe the child stays, its Taichi runtime warm, and makes further replays on request
(:meth:`ProbeWorker.submit`, :meth:`ProbeWorker.collect`) until :meth:`ProbeWorker.close`: the bending
plasticity refit's yield-angle search makes its second replay there while this process makes its first
(:func:`sysid.diagnose.plasticity_refit.fit_yield_angle` ``prefetch``). A request carries the calibration's
nominal values, the replay's parameters and its start (:class:`~sysid.observation.Resume`); the child sets
the same nominal values on its copy of the model, so that the replay is the one this process would make.
A request may also name a function of this package (:meth:`ProbeWorker.call`), called in the child with its copy of the
model, a dict the child keeps for its life (e.g. a model it built for another gel law) and the request's arguments:
``thinshell sysid`` makes the other gel law's replays with tangents there while this process makes the scene's law's
(:func:`sysid.gel_law.replay_beside`).
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
from typing import Any, Callable, Mapping, Sequence

from sysid.calibration_secant import (CONTACT_ONSET_PARAMETERS, SECANT_PARAMETERS, FirstReplay, first_probe_values,
                                      resume_before_contact)


def calibration_probe(model, params: Sequence[str], *, secant_replays: int, max_replays: int | None,
                      max_time: float | None, names: Sequence[str] = SECANT_PARAMETERS) -> "ProbeWorker | None":
    """A :class:`ProbeWorker` for :func:`sysid.calibration.calibrate` of ``model`` with ``params``, or None where
    its replay would not be the secant stage's first one or cannot run: no secant replay (``secant_replays``
    0), a parameter fit that may step (parameters with a budget ``max_replays`` other than one replay, or a
    time budget ``max_time``), no secant parameter ``names`` left outside ``params``, or Taichi already started
    in this process (a forked child could not run it). Through a drive the child replays through the one
    ``model`` holds when it is forked (set it first). Used by ``thinshell diagnose``'s signature stage and by
    ``thinshell sysid`` (:func:`sysid.fit_recording.fit_recording`)."""
    from sim_core.ti_backend import current_arch

    if not (secant_replays > 0 and max_time is None and (not params or max_replays == 1) and current_arch() is None):
        return None
    names = tuple(n for n in names if n not in tuple(params))
    return ProbeWorker(model, params, names) if names else None


class ProbeWorker:
    """The secant stage's first replay made in a forked child process, which then makes further replays on
    request until closed (module docstring).

    Args:
        model: the recording's :class:`~sysid.observation.ObservationModel`, before its simulation has
            started Taichi (the child gets a copy).
        params: the calibration's fitted parameters (their scene values are the fit's start).
        names: the secant stage's parameters (the calibration's ``secant_params`` not in ``params``).

    Raises:
        ValueError: no secant parameter, or this process has started Taichi (the child could not run it).
    """

    def __init__(self, model, params: Sequence[str], names: Sequence[str] = SECANT_PARAMETERS) -> None:
        from sim_core.ti_backend import current_arch

        names = tuple(n for n in names if n not in tuple(params))
        if not names:
            raise ValueError("ProbeWorker: no secant parameter left to probe")
        if current_arch() is not None:
            raise ValueError("ProbeWorker: Taichi is started in this process; a forked child cannot run it")
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe(duplex=True)
        self._process = ctx.Process(target=_probe, args=(model, tuple(params), names, child), daemon=True)
        self._process.start()
        child.close()
        self._result: FirstReplay | None = None
        self._received = False
        self._pending = False
        self._closed = False

    def result(self) -> FirstReplay | None:
        """The replay (waits for the child), or None when the child failed (a diverged replay, an error:
        the stage then replays it here and meets the same failure; the child is then ended). Later calls
        return the same."""
        if not self._received:
            self._received = True
            self._result = self._receive()
            if self._result is None:
                self.close()
        return self._result

    @property
    def available(self) -> bool:
        """Whether the child takes a request now: its probe is sent, no request is pending, not closed."""
        return self._received and not self._pending and not self._closed

    def submit(self, nominal: Mapping[str, float], params: Mapping[str, float], resume: Any = None,
               kinematic: bool = False) -> bool:
        """Ask the child for the replay of ``params`` started at ``resume`` (a :class:`~sysid.observation.Resume`
        or None: from t = 0), with ``nominal`` as the model's nominal values (``ObservationModel.set_nominal``:
        the calibration's parameters); with ``kinematic`` the recorded pose imposed (the drive the child holds set
        aside for it, as :func:`sysid.calibration.kinematic_reference` does). False (nothing asked) when the child
        is not :attr:`available`."""
        return self.call(_replay_request, dict(nominal), dict(params), resume, bool(kinematic))

    def call(self, fn: Callable[..., Any], *args: Any) -> bool:
        """Ask the child for ``fn(model, cache, *args)`` (``fn`` a module-level function, ``args`` picklable; ``model``
        the child's copy of the model, ``cache`` a dict the child keeps until closed), its value sent back through
        :meth:`collect` (None where it raised). False (nothing asked) when the child is not :attr:`available`."""
        if not self.available:
            return False
        try:
            self._conn.send((fn, args))
        except (OSError, ValueError, TypeError, AttributeError):  # a closed pipe; an argument that does not pickle
            self.close()
            return False
        self._pending = True
        return True

    def collect(self) -> Any:
        """The submitted replay (a :class:`~sysid.observation.SimTrace` without states) or :meth:`call`'s value (waits
        for the child), or None when it failed or nothing was submitted (the caller then replays it itself)."""
        if not self._pending:
            return None
        self._pending = False
        out = self._receive()
        if out is None:
            self.close()
        return out

    def _receive(self) -> Any:
        if self._closed:
            return None
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            return None

    def close(self) -> None:
        """End the child (after its last reply, or stopped where a calibration ended before its secant stage).
        Later calls do nothing."""
        if self._closed:
            return
        self._closed = True
        self._conn.close()
        if self._process.is_alive():
            self._process.join(timeout=1.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()


def _probe(model, params: tuple[str, ...], names: tuple[str, ...], conn) -> None:
    """The child: replay the secant stage's first parameters from the scene values and send a
    :class:`~sysid.calibration_secant.FirstReplay` (None on failure), then serve requests (:func:`_serve`)."""
    out = None
    try:
        model.sensor_calibration = None
        model.reset_nominal()
        base = {n: float(model.parameter_value(n)) for n in params}
        values = first_probe_values(model, base, names)
        shared = set(names) <= set(CONTACT_ONSET_PARAMETERS)
        trace = model.simulate(values, keep_states=shared)
        resume = resume_before_contact(trace) if shared else None
        out = FirstReplay(values, dataclasses.replace(trace, states=None), resume)
    except Exception:  # noqa: BLE001 -- any failure: the parent replays it itself and reports it there
        out = None
    try:
        conn.send(out)
        if out is not None:
            _serve(model, conn)
    except (EOFError, OSError):
        return
    finally:
        conn.close()


def _serve(model, conn) -> None:
    """The child after its probe: for each request ``(fn, args)`` send ``fn(model, cache, *args)`` (None on failure),
    until the parent closes its end."""
    cache: dict[str, Any] = {}
    while True:
        fn, args = conn.recv()
        try:
            out = fn(model, cache, *args)
        except Exception:  # noqa: BLE001 -- any failure: the parent replays it itself and reports it there
            out = None
        conn.send(out)


def _replay_request(model, cache: dict, nominal: Mapping[str, float], params: Mapping[str, float], resume: Any,
                    kinematic: bool) -> Any:
    """:meth:`ProbeWorker.submit`'s replay in the child: ``params`` replayed from ``resume`` with ``nominal`` as the
    model's nominal values, kinematic where asked; the trace without states."""
    stiffness, damping = model.drive_stiffness, model.drive_damping
    try:
        model.reset_nominal()
        model.set_nominal(nominal)
        if kinematic:
            model.set_drive_stiffness(math.inf)
        return dataclasses.replace(model.simulate(params, resume=resume), states=None)
    finally:
        model.set_drive_stiffness(stiffness, damping)
