"""The versioned JSON form of a fit (``fit.json``): fit, metrics, diagnostics and provenance kept apart.

Schema ``thinshell.sysid.fit`` version 1::

    {
      "schema": "thinshell.sysid.fit", "schema_version": 1,
      "fit": {
        "parameters": {name: {"initial", "value", "sigma", "sigma_scaled", "sigma_robust", "sigma_log",
                              "space": "log"|"linear", "lower", "upper",
                              "identified": false where the recording does not identify it (sysid.identifiability:
                                            its interval reaches a bound of its prior range), else true; null
                                            without a robust sigma,
                              "interval": {"lower", "upper", "prior": [lo, hi], "identified", "open_below",
                                           "open_above", "source": "linearised"|"profile", "outside_prior",
                                           "profile": [{"delta_u", "value", "z", "delta_cost"}]} | null,
                              "held": true where the fit held it (no step along it) at its last accepted point
                                      (sysid.fit.fit hold_unidentified)}},
        "correlation": {"names": [...], "matrix": [[...]]} | null,
        "covariance_u": [[...]] | null,       # Gauss-Newton (J^T W J)^-1 in the search coordinates
        "robust": {"method": "hac"|"block_bootstrap"|"hac+nuisance"|..., "lag_bins", "lag_s", "bin_s", "bins",
                   "resamples", "inflation": [...], "covariance_u": [[...]],
                   # with "+nuisance" (sysid.fit.fit nuisance): the priors, d u / d phi and the time part's inflation
                   "nuisance_prior": {name: s}, "nuisance_shift_u": {name: [...]}, "time_inflation": [...]
                  } | null   # sysid.covariance
      },
      "metrics": {"cost_initial", "cost_final", "reduced_chi2", "residual_count",
                  "rms_initial": {channel: {...}}, "rms_final": {channel: {...}}},
      "diagnostics": {"status", "message", "iterations", "nfev", "njev", "sim_runs" (the profile's replays
                      included), "profile_runs", "sim_time_s", "wall_time_s", "jacobian", "global_phase", "channels",
                      "step_count", "dt",
                      "loss_history": [{"eval", "phase", "cost", "time_s", "values"}], "warnings"},
      "provenance": {"bag", "bag_sha256", "scene", "t_max", "seed", "git_revision", "git_dirty",
                     "versions": {...}, "command", "created_utc", "host"}
    }

Infinite costs (failed replays) are written as null. ``fit.robust`` and ``sigma_robust`` (the 1-sigma
that holds under model error, :mod:`sysid.covariance`) were added within version 1: a document
without them still validates (they read as null); so were ``identified``'s judgement against the prior range and
``interval`` (:mod:`sysid.identifiability`).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import platform
import shutil
import sys
import uuid
from importlib import metadata
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError
from sim_core.provenance import git_revision

SCHEMA = "thinshell.sysid.fit"
SCHEMA_VERSION = 1
TOP_KEYS = ("schema", "schema_version", "fit", "metrics", "diagnostics", "provenance")
SECTION_KEYS = {
    "fit": ("parameters", "correlation", "covariance_u"),
    "metrics": ("cost_initial", "cost_final", "reduced_chi2", "residual_count", "rms_initial", "rms_final"),
    "diagnostics": ("status", "message", "iterations", "nfev", "njev", "sim_runs", "sim_time_s", "wall_time_s",
                    "jacobian", "global_phase", "channels", "step_count", "dt", "loss_history", "warnings"),
    "provenance": ("bag", "bag_sha256", "scene", "t_max", "seed", "git_revision", "git_dirty", "versions",
                   "command", "created_utc", "host"),
}
VERSIONED_PACKAGES = ("numpy", "scipy", "cma", "rosbags", "mcap", "matplotlib", "taichi")


def _finite(x: Any) -> Any:
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.ndarray):
        return [_finite(v) for v in x.tolist()] if x.ndim else _finite(x.item())
    if isinstance(x, Mapping):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def package_versions(packages: Sequence[str] = VERSIONED_PACKAGES) -> dict[str, str | None]:
    """Installed versions of the packages a fit depends on (None when not installed), plus Python."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in packages:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def provenance(evidence: Any, seed: int, t_max: float | None, argv: Sequence[str] | None = None,
               scene: str | None = None) -> dict[str, Any]:
    """Provenance block: bag path and SHA-256 (from the evidence), the recording map it was read through (or
    None), scene, seed, git, versions, command."""
    rev, dirty = git_revision()
    src = evidence.source
    return {
        "bag": str(src.bag_path), "bag_sha256": src.sha256,
        "recording_map": str(src.recording_map) if src.recording_map is not None else None,
        "scene": scene if scene is not None else (str(src.scene_path) if src.scene_path else None),
        "t_max": t_max, "seed": int(seed), "git_revision": rev, "git_dirty": dirty, "versions": package_versions(),
        "command": list(argv) if argv is not None else list(sys.argv),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "host": platform.node(),
    }


def fit_document(result: Any, prov: Mapping[str, Any]) -> dict[str, Any]:
    """The ``fit.json`` document of a :class:`sysid.fit.FitResult`."""
    params = {}
    for spec in result.specs:
        n = spec.name
        params[n] = {
            "initial": result.initial[n], "value": result.values[n],
            "sigma": result.sigma[n] if result.sigma else None,
            "sigma_scaled": result.sigma_scaled[n] if result.sigma_scaled else None,
            "sigma_robust": (getattr(result, "sigma_robust", None) or {}).get(n),
            "sigma_log": (result.sigma_log or {}).get(n), "space": "log" if spec.log else "linear",
            "identified": (None if not getattr(result, "sigma_robust", None)
                           else n not in getattr(result, "not_identified", ())),
            "interval": (None if n not in (getattr(result, "intervals", None) or {})
                         else result.intervals[n].summary()),
            "held": n in getattr(result, "held", ()),
            "lower": spec.lower, "upper": spec.upper,
        }
    corr = None
    if result.correlation is not None:
        corr = {"names": list(result.names), "matrix": result.correlation}
    history = [{"eval": i, "phase": e.phase, "cost": e.cost, "time_s": e.time_s,
                "values": {s.name: s.to_value(float(u)) for s, u in zip(result.specs, e.u)}}
               for i, e in enumerate(result.history)]
    robust = getattr(result, "robust", None)
    robust_doc = None if robust is None else {**robust.summary(), "covariance_u": robust.covariance_u}
    doc = {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION,
        "fit": {"parameters": params, "correlation": corr, "covariance_u": result.covariance_u, "robust": robust_doc},
        "metrics": {"cost_initial": result.cost_initial, "cost_final": result.cost_final,
                    "reduced_chi2": result.reduced_chi2, "residual_count": result.residual_count,
                    "rms_initial": result.rms_initial, "rms_final": result.rms_final},
        "diagnostics": {"status": result.status, "message": result.message, "iterations": result.iterations,
                        "nfev": result.nfev, "njev": result.njev, "sim_runs": result.sim_runs,
                        "sim_time_s": result.sim_time_s, "wall_time_s": result.wall_time_s,
                        "jacobian": result.jacobian, "global_phase": result.global_phase,
                        "channels": list(result.channels), "step_count": result.step_count, "dt": result.dt,
                        "profile_runs": getattr(result, "profile_runs", 0),
                        "loss_history": history, "warnings": list(result.warnings)},
        "provenance": dict(prov),
    }
    return _finite(doc)


def validate_fit_document(doc: Mapping[str, Any], where: str = "fit.json") -> None:
    """Check the schema name, version and the keys of every section.

    Raises:
        CalibrationError: wrong schema / version, or a missing key (named with its section).
    """
    if doc.get("schema") != SCHEMA:
        raise CalibrationError(f"{where}: schema is {doc.get('schema')!r}, expected {SCHEMA!r}")
    if doc.get("schema_version") != SCHEMA_VERSION:
        raise CalibrationError(f"{where}: schema_version {doc.get('schema_version')!r} is not supported "
                               f"(supported: {SCHEMA_VERSION})")
    for key in TOP_KEYS:
        if key not in doc:
            raise CalibrationError(f"{where}: missing key {key!r}")
    for section, keys in SECTION_KEYS.items():
        for key in keys:
            if key not in doc[section]:
                raise CalibrationError(f"{where}: missing key {section}.{key}")


def write_fit_json(path: str | Path, doc: Mapping[str, Any]) -> Path:
    """Validate and write ``doc`` as indented JSON (strict: no NaN / Infinity)."""
    validate_fit_document(doc, str(path))
    path = Path(path)
    path.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path


def load_fit_json(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``fit.json``.

    Raises:
        CalibrationError: missing file, invalid JSON, or a schema violation (names the file).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise CalibrationError(f"{path}: fit result does not exist") from err
    except json.JSONDecodeError as err:
        raise CalibrationError(f"{path}: not valid JSON ({err})") from err
    validate_fit_document(doc, str(path))
    return doc


@contextlib.contextmanager
def staged_directory(out: str | Path, force: bool) -> Iterator[Path]:
    """Fill a hidden sibling of ``out`` inside the ``with`` block, then rename it into place.

    The result appears whole or not at all: on any exception the staging directory is removed and
    ``out`` is left as it was.

    Args:
        out: final result directory.
        force: replace an existing ``out`` (moved aside first, then deleted).

    Yields:
        the staging directory (empty).

    Raises:
        FileExistsError: ``out`` exists (e.g. appeared while the work ran) and not ``force``; the
            staging directory is removed.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:8]}"
    staging.mkdir()
    try:
        yield staging
        _publish_directory(staging, out, force)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def _publish_directory(staging: Path, out: Path, force: bool) -> None:
    """Rename ``staging`` to ``out`` (atomic on one file system), replacing ``out`` when ``force``."""
    trash = None
    if out.exists() or out.is_symlink():
        if not force:
            raise FileExistsError(f"{out} appeared while working; the result is not written")
        trash = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(out, trash)
    os.replace(staging, out)
    if trash is not None:
        shutil.rmtree(trash, ignore_errors=True) if trash.is_dir() else trash.unlink()
