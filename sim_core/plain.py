"""Plain Python values for YAML / JSON writers (``yaml.safe_dump`` cannot write NumPy types)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np


def plain(value: Any) -> Any:
    """``value`` with mappings, sequences and arrays turned into dicts and lists of Python scalars,
    NumPy scalars into Python ones and paths into strings (recursively)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value
