"""``thinshell sysid`` defaults from starts 30 % above and 30 % below the truth on this simulator's own press-slide
(issue 49 item 4): the fitted materials land near the truth and near each other, whatever the start, and every
truth lies inside the reported robust 2-sigma interval.

The recording is :mod:`tests.sysid.test_sysid_drive`'s: the benchmark card pressed and slid through a concealed
2,000 N/m arm, noise at the reference bags' levels. The start is the scene a user would hand over: ``scene.yaml``
rewritten with all three materials x1.3 or x0.7 (the stick regularisation ``contact.eps_v`` at the scene's default,
as a user's scene has it).
"""

from __future__ import annotations

import json

import pytest
import yaml

from sysid.cli import sysid_main
from tests.sysid.simbag import TRUE_PARAMS, scene_with
from tests.sysid.test_sysid_drive import FITTED, arm_bag  # noqa: F401 (the recording, a module fixture here too)

STARTS = (1.3, 0.7)


@pytest.fixture(scope="module")
def fits(arm_bag, tmp_path_factory):  # noqa: F811 (arm_bag is the fixture imported above)
    """fit.json of ``thinshell sysid`` (defaults) from each start in :data:`STARTS`."""
    out = {}
    for factor in STARTS:
        where = tmp_path_factory.mktemp(f"start_{factor}")
        bag = where / "bag"
        bag.mkdir()
        for f in arm_bag.iterdir():
            (bag / f.name).write_bytes(f.read_bytes())
        (bag / "scene.yaml").write_text(yaml.safe_dump(scene_with({n: TRUE_PARAMS[n] * factor for n in FITTED})))
        rc = sysid_main([str(bag), "--out", str(where / "fit"), "--quiet"])
        assert rc == 0
        out[factor] = json.loads((where / "fit" / "fit.json").read_text())
    return out


def test_the_materials_from_starts_30_percent_above_and_below_agree_and_cover_the_truth(fits):
    """Both starts: the gel-sheet friction within 5 % of the truth, the gel modulus within 8 % (0.974 / 0.957; the
    robust sigma is 0.11-0.12 x the truth: a flat valley where the modulus trades against the marker scales) and the
    two moduli within 5 % of each other; every truth inside the robust 2-sigma interval. From x1.3 the calibration's
    secant stage takes a stick regularisation ``contact.eps_v`` of 14.7 mm/s at the start's materials (the recording's
    is 10); held there, the modulus ended at 0.835 x the truth, 2.8 robust sigma away and 12.7 % from the x0.7 fit's.
    Fitted with the materials (``--fit-eps-v``, default; its column the replay's tangent) it comes back within 10 % of
    the recording's (10.1 mm/s; 10.5 with a forward-difference column) and the modulus to 0.974 (0.949), in 6
    replays (13). From x0.7 the stage keeps the scene's 10 mm/s, which is then held (docs/benchmarks_log.md,
    session 53, 49start).

    The bending stiffness, which this 6 mm slide does not load (its Jacobian column about 1/400 of the modulus'), is
    held at its start, flagged not identified, with an interval wider than its value that holds the truth: the
    data cannot place it, so the honest answer is the scene's (the start's) value with that interval, not a value
    within 10 % of a truth the recording does not show."""
    modulus = {}
    for factor, doc in fits.items():
        params = doc["fit"]["parameters"]
        for name in FITTED:
            p = params[name]
            assert abs(p["value"] - TRUE_PARAMS[name]) < 2.0 * p["sigma_robust"], (factor, name, p)
        friction = params["friction.gel_sheet"]["value"]
        assert friction == pytest.approx(TRUE_PARAMS["friction.gel_sheet"], rel=0.05), factor
        modulus[factor] = params["gel.youngs_modulus"]["value"]
        assert modulus[factor] == pytest.approx(TRUE_PARAMS["gel.youngs_modulus"], rel=0.08), (factor, params)
        secant = doc["diagnostics"]["sensor_calibration"]["secant"]
        if secant["accepted"]:  # found at the start's materials: fitted with them, back near the recording's
            assert params["contact.eps_v"]["value"] == pytest.approx(0.01, rel=0.10), (factor, params["contact.eps_v"])
        else:  # the stage kept the scene's value: nothing of the start in it, held
            assert "contact.eps_v" not in params, (factor, secant)
            assert "contact.eps_v" not in doc["diagnostics"]["sensor_calibration"]["params"], (factor, secant)
        bending = params["sheet.bending_stiffness"]
        assert bending["held"] is True and bending["identified"] is False, (factor, bending)
        assert bending["value"] == pytest.approx(TRUE_PARAMS["sheet.bending_stiffness"] * factor, rel=1e-9)
    assert modulus[1.3] == pytest.approx(modulus[0.7], rel=0.05), modulus
    assert fits[1.3]["diagnostics"]["sensor_calibration"]["secant"]["accepted"]  # the case the fit of eps_v is for
