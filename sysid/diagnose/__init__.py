"""Missing-physics diagnosis (SYSID.md): score tests of a candidate library, location, refit, report."""

from __future__ import annotations

from sysid.diagnose.candidates import EFFECTS
from sysid.diagnose.engine import Settings, diagnose, run_diagnosis
from sysid.diagnose.schema import validate_report

__all__ = ["EFFECTS", "Settings", "diagnose", "run_diagnosis", "validate_report"]
