"""The calibration's secant probe made in a forked process (sysid.diagnose.probe_worker): bit for bit the
replay this process makes, on the reference recording nominal_s101 (first 0.8 s, coarse gel)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from sysid.diagnose.probe_worker import calibration_probe
from sysid.diagnose.signature_engine import SignatureSettings, probe_worker_for

REPO = Path(__file__).resolve().parents[3]

CHILD = """
import sys
import numpy as np
from sysid.calibration_secant import first_probe_values
from sysid.diagnose.probe_worker import ProbeWorker
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel

model = ObservationModel(load_evidence(sys.argv[1]), dt=0.01, t_max=0.8, simulation={"gel_resolution": [4, 3, 2]},
                         arch="cpu")
worker = ProbeWorker(model, ("gel.youngs_modulus",))
made = worker.result()
assert made is not None and made.trace.states is None
base = {"gel.youngs_modulus": model.parameter_value("gel.youngs_modulus")}
values = first_probe_values(model, base, ("contact.eps_v",))
assert made.values == values, (made.values, values)
here = model.simulate(values)
for ch in ("markers_xyz", "markers_uv", "wrench", "sheet_points"):
    assert np.array_equal(getattr(made.trace, ch), getattr(here, ch)), ch
assert 0 < made.resume.step < model.step_count and not np.any(made.resume.prefix.wrench)
assert worker.result() is made
# later requests: the child sets the nominal values asked for and makes the replay this process makes
model.set_nominal(base)
stiffer = {**values, "gel.youngs_modulus": 1.1 * base["gel.youngs_modulus"]}
step = {**values, "contact.eps_v": values["contact.eps_v"] / 3.0}
for params, resume in ((stiffer, None), (step, made.resume)):
    assert worker.available and worker.submit(base, params, resume) and not worker.available
    there, here = worker.collect(), model.simulate(params, resume=resume)
    assert there.states is None and worker.available
    for ch in ("markers_xyz", "markers_uv", "wrench", "sheet_points"):
        assert np.array_equal(getattr(there, ch), getattr(here, ch)), ch
assert worker.collect() is None  # nothing submitted
worker.close()
assert not worker.available and not worker.submit(base, step) and worker.collect() is None
print("same replay; later replays resume at step", made.resume.step)
"""


def test_probe_made_in_a_forked_process_is_the_replay_made_here():
    """Run in a process of its own: the worker forks before Taichi starts (a test process may have
    started it already). The child's later replays on request are those made here too."""
    from tests.sysid.conftest import reference_bag

    proc = subprocess.run([sys.executable, "-c", CHILD, str(reference_bag("nominal_s101"))], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "same replay" in proc.stdout


def test_probe_worker_only_where_its_replay_is_the_secant_stage_first_one():
    """None without the setting, with a fit that may step, with a time budget, or with the stick
    regularisation among the fitted parameters; no fork once Taichi runs here. A drive does not stop it (the
    child replays through the drive the model holds when forked: signature_engine.prepare sets it first)."""
    from sim_core.ti_backend import current_arch
    from sysid.diagnose.probe_worker import ProbeWorker

    on = SignatureSettings(probe_worker=True)
    params = ("gel.youngs_modulus",)
    for settings in (SignatureSettings(), dataclasses.replace(on, calibration_max_replays=3),
                     dataclasses.replace(on, calibration_max_time=10.0),
                     dataclasses.replace(on, calibration_secant_replays=0), dataclasses.replace(on, calibrate=False)):
        assert probe_worker_for(None, params, settings) is None
    if current_arch() is None:
        assert probe_worker_for(None, params + ("contact.eps_v",), on) is None
    with pytest.raises(ValueError, match="no secant parameter"):
        ProbeWorker(None, ("contact.eps_v",))


def test_diagnose_command_makes_the_probe_beside_unless_asked_for_one_process():
    from sysid.diagnose.cli import build_parser, signature_settings

    assert signature_settings(build_parser().parse_args(["bag"])).probe_worker
    assert not signature_settings(build_parser().parse_args(["bag", "--one-process"])).probe_worker


def test_sysid_command_makes_the_probe_beside_unless_asked_for_one_process():
    from sysid.cli import build_parser, fit_options
    from sysid.fit_recording import FitOptions, available_cores

    assert FitOptions().probe_worker and fit_options(build_parser().parse_args(["bag", "--workers", "2"])).probe_worker
    assert not fit_options(build_parser().parse_args(["bag", "--one-process"])).probe_worker
    # --workers defaults to the cores this process may run on; one is one process
    default = fit_options(build_parser().parse_args(["bag"]))
    assert default.workers == available_cores() and default.probe_worker == (available_cores() > 1)
    assert not fit_options(build_parser().parse_args(["bag", "--workers", "1"])).probe_worker
    # none where its replay would not be the secant stage's first: the stick regularisation fitted, no secant
    # replay, a time budget, or a parameter fit that may step
    for params, replays, budget, most in ((("contact.eps_v",), 2, None, 1), ((), 0, None, 1), ((), 2, 10.0, 1),
                                          (("gel.youngs_modulus",), 2, None, 3)):
        assert calibration_probe(None, params, secant_replays=replays, max_replays=most, max_time=budget) is None


PREPARED = """
import sys
import numpy as np
import sysid.observation as observation
from sysid.diagnose.signature_engine import SignatureSettings, prepare, without_replays

made_here = []
simulate = observation.ObservationModel.simulate
observation.ObservationModel.simulate = lambda self, *a, **k: made_here.append(1) or simulate(self, *a, **k)
common = dict(t_max=0.8, simulation={"gel_resolution": [4, 3, 2]})
prepared = prepare(sys.argv[1], SignatureSettings(probe_worker=True, **common))
assert prepared.calibration.drive.compliant and prepared.calibration.secant.accepted
# the drive's calibration started no Taichi here, so the probe process forked: here the start replay and the secant
# step; the probe and the kinematic reference there
assert len(made_here) == 2, len(made_here)
# after the kinematic reference the probe process replays through the drive again (the refits' later replays)
worker = prepared.replays
assert worker.submit(prepared.calibration.params, prepared.calibration.params) and worker.collect().drive is not None
beside = without_replays(prepared)
made_here.clear()
alone = prepare(sys.argv[1], SignatureSettings(probe_worker=False, **common))
assert len(made_here) == 4, len(made_here)
assert beside.calibration.params == alone.calibration.params
for ch, values in alone.recording.reference.items():
    assert np.array_equal(beside.recording.reference[ch], values), ch
for ch, values in alone.prediction.items():
    assert np.array_equal(beside.prediction[ch], values), ch
print("the same calibrated replay and kinematic reference")
"""


def test_diagnosis_makes_its_kinematic_reference_beside_the_secant_step_with_the_same_result():
    """``signature_engine.prepare`` with the probe process, through the drive: the drive's calibration reads the
    sensor's normal without starting Taichi, so the calibration's secant probe still forks (until session 53 the
    normal was read from a started simulation, and every diagnosis through a drive made its probe in one process);
    the kinematic reference (the recorded pose imposed, at the calibrated values) is replayed there beside the
    calibration's secant step, after which that process replays through the drive again; the prepared recording is
    bit for bit the one-process one (nominal_s101's first 0.8 s, coarse gel; the step is accepted there)."""
    from tests.sysid.conftest import reference_bag

    proc = subprocess.run([sys.executable, "-c", PREPARED, str(reference_bag("nominal_s101"))], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "the same calibrated replay and kinematic reference" in proc.stdout
