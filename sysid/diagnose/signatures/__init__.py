"""Signature tests of the missing-physics candidates (SYSID.md "Typical signatures").

:func:`run_signature_tests` runs every test on one :class:`Recording`; :mod:`.null` turns their
statistics into decisions against default thresholds or a null calibrated on recordings the user
declares normal.
"""

from __future__ import annotations

from sysid.diagnose.signatures.base import Recording, SignatureResult
from sysid.diagnose.signatures.damping import damping_test
from sysid.diagnose.signatures.friction import stiction_test
from sysid.diagnose.signatures.sensor import force_bias_test, lens_test
from sysid.diagnose.signatures.sheet import adhesion_test, plasticity_test
from sysid.diagnose.signatures.timing import timing_tests


def run_signature_tests(rec: Recording) -> dict[str, SignatureResult]:
    """Every signature test on ``rec``: effect -> result (not yet decided)."""
    latency, visco = timing_tests(rec)
    out = [lens_test(rec), force_bias_test(rec), latency, visco, damping_test(rec), plasticity_test(rec),
           adhesion_test(rec), stiction_test(rec)]
    return {r.effect: r for r in out}


__all__ = ["Recording", "SignatureResult", "run_signature_tests"]
