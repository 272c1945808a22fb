"""``thinshell sysid --workers``: the independent replays spread over two processes give the one-process fit.

This simulator's own deep press-slide of the card scene made with the Green-strain gel, its ``scene.yaml`` naming no
law (:data:`tests.sysid.test_gel_law.DEEP_PRESS_SLIDE`; 28 steps): ``thinshell sysid``'s default ``--gel-element auto``
compares the scene's law with the Green-strain law at the fit's start, the Green-strain law leads after one predicted
step, so both laws take a second step (:func:`sysid.gel_law.restep`). With ``--workers 2`` the calibration's probe
process makes the Green-strain law's two replays with tangents (its start, beside the calibration's last replay, and
its second step, beside the scene's law's) while this process makes the scene's law's; with ``--workers 1`` this
process makes all of them one after the other. The fitted values, their sigmas, the residuals and the choice are the
same bit for bit, and the parent process makes two replays with tangents fewer. Each command runs in a process of its
own (the probe process forks before Taichi starts, which a test process may have started).

About 40 CPU s (two sysid runs of the 28-step recording, each with its Taichi start); 116 s wall on the VM at
load ~7.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.sysid.simbag import TRUE_PARAMS, add_noise, scene_with, simulate_streams, targets_from_segments, write_bag
from tests.sysid.test_gel_law import DEEP_PRESS_SLIDE

REPO = Path(__file__).resolve().parents[2]

COUNTED = """
import sys
import sysid.jacobians as jacobians
from sysid.cli import sysid_main

made_here = []
make = jacobians.TangentReplay.make.__func__
jacobians.TangentReplay.make = classmethod(lambda cls, *a, **k: made_here.append(1) or make(cls, *a, **k))
rc = sysid_main(sys.argv[1:])
print("replays with tangents here:", len(made_here))
sys.exit(rc)
"""


@pytest.fixture(scope="module")
def green_strain_bag(tmp_path_factory):
    """This simulator's deep press-slide made with the Green-strain gel; its ``scene.yaml`` names no law."""
    scene = scene_with(TRUE_PARAMS)
    made_with = {**scene, "simulation": {**scene.get("simulation", {}), "gel_element": "green_strain"}}
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), DEEP_PRESS_SLIDE)
    streams = add_noise(simulate_streams(made_with, TRUE_PARAMS, targets), seed=11)
    return write_bag(tmp_path_factory.mktemp("green_strain") / "bag", scene, streams)


def _sysid(bag: Path, out: Path, workers: int) -> tuple[dict, int]:
    """fit.json of ``thinshell sysid BAG --workers WORKERS`` (the modulus, one fit evaluation) in a process of its
    own, and the replays with tangents that process made."""
    proc = subprocess.run([sys.executable, "-c", COUNTED, str(bag), "--out", str(out), "--params", "gel.youngs_modulus",
                           "--max-nfev", "1", "--quiet", "--workers", str(workers)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    made = int(proc.stdout.rsplit("replays with tangents here:", 1)[1].split()[0])
    return json.loads((out / "fit.json").read_text()), made


def _untimed(doc):
    """``doc`` (fit.json's JSON) without its wall-time entries (keys ending in ``time_s``)."""
    if isinstance(doc, dict):
        return {k: _untimed(v) for k, v in doc.items() if not k.endswith("time_s")}
    return [_untimed(v) for v in doc] if isinstance(doc, list) else doc


def test_two_workers_make_the_one_process_fit_with_the_other_laws_replays_beside(green_strain_bag, tmp_path):
    alone, made_alone = _sysid(green_strain_bag, tmp_path / "one", 1)
    beside, made_beside = _sysid(green_strain_bag, tmp_path / "two", 2)
    law = alone["diagnostics"]["gel_law"]
    assert law["element"] == "green_strain" and law["choice"]["restepped"], law
    assert beside["diagnostics"]["gel_law"] == law
    assert beside["fit"] == alone["fit"]
    assert beside["metrics"]["rms_final"] == alone["metrics"]["rms_final"]
    assert _untimed(beside["diagnostics"]["sensor_calibration"]) == _untimed(alone["diagnostics"]["sensor_calibration"])
    # one process: the calibration's last replay, the other law's start and both laws' second steps (the fit's one
    # evaluation takes the chosen law's start); two: the other law's two made beside
    assert made_alone - made_beside == 2, (made_alone, made_beside)
