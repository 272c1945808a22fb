"""The JSON contract of ``thinshell diagnose`` (SYSID.md "Output contract") and its validation.

Top-level keys exactly ``schema_version, bag, baseline, mismatch, candidates, explained_by, refit`` plus
``extra``; each object holds at least the sub-keys of the contract (more keys are allowed inside the objects).
``explained_by`` is ``[]``, ``["unexplained"]`` or effect names of the vocabulary. ``schema_version`` is
:data:`SCHEMA_VERSION`; ``extra.pipeline`` says which stage of the one pipeline named
(:mod:`sysid.diagnose.pipeline`: ``stage``, the ``drive`` that decided it, ``why``, ``not_applied``).

Versions: 1 (to session 50): no ``schema_version``; two engines, ``extra.engine`` on the signature engine's
reports only. 2: one pipeline, ``schema_version`` and ``extra.pipeline`` on every report.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from sim_core.errors import CalibrationError
from sysid.diagnose.candidates import EFFECTS

SCHEMA_VERSION = 2
"""Version of the report's schema (module docstring)."""

TOP_KEYS = ("schema_version", "bag", "baseline", "mismatch", "candidates", "explained_by", "refit")
PIPELINE_KEYS = ("stage", "drive", "why", "not_applied")
STAGES = ("score", "signatures")
"""The pipeline's stages (:mod:`sysid.diagnose.pipeline`), the values of ``extra.pipeline.stage``."""
SUB_KEYS = {"baseline": ("params", "rms"), "mismatch": ("detected", "windows_s", "channels", "markers"),
            "refit": ("params", "rms", "heldout_rms_before", "heldout_rms_after")}
CANDIDATE_KEYS = ("effect", "statistic", "p_value")


def _number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def validate_report(doc: Mapping[str, Any]) -> None:
    """Check a diagnosis report against the contract.

    Raises:
        CalibrationError: the first violation, naming the key path.
    """
    def fail(msg: str) -> None:
        raise CalibrationError(f"diagnosis report: {msg}")

    if not isinstance(doc, Mapping):
        fail(f"must be an object, got {type(doc).__name__}")
    missing = [k for k in TOP_KEYS if k not in doc]
    if missing:
        fail(f"missing top-level key {missing[0]!r}")
    unknown = sorted(set(doc) - set(TOP_KEYS) - {"extra"})
    if unknown:
        fail(f"unknown top-level key {unknown[0]!r} (extra keys belong under 'extra')")
    if doc["schema_version"] != SCHEMA_VERSION:
        fail(f"'schema_version' is {doc['schema_version']!r}; this version of thinshell reads {SCHEMA_VERSION}")
    if not isinstance(doc["bag"], str):
        fail("'bag' must be a string")
    pipe = doc.get("extra", {}).get("pipeline") if isinstance(doc.get("extra"), Mapping) else None
    if not isinstance(pipe, Mapping):
        fail("missing object 'extra.pipeline' (the stage that named, and why)")
    for k in PIPELINE_KEYS:
        if k not in pipe:
            fail(f"missing key 'extra.pipeline.{k}'")
    if pipe["stage"] not in STAGES:
        fail(f"'extra.pipeline.stage' = {pipe['stage']!r} is none of {', '.join(STAGES)}")
    for obj, keys in SUB_KEYS.items():
        if not isinstance(doc[obj], Mapping):
            fail(f"'{obj}' must be an object")
        for k in keys:
            if k not in doc[obj]:
                fail(f"missing key '{obj}.{k}'")
    for obj in ("baseline", "refit"):
        for k in ("params", "rms"):
            v = doc[obj][k]
            if not isinstance(v, Mapping):
                fail(f"'{obj}.{k}' must be an object")
    for k in ("heldout_rms_before", "heldout_rms_after", "heldout_rms_null"):
        v = doc["refit"].get(k)
        if v is not None and not _number(v):
            fail(f"'refit.{k}' must be a number or null, got {v!r}")
    m = doc["mismatch"]
    if not isinstance(m["detected"], bool):
        fail("'mismatch.detected' must be true or false")
    if not isinstance(m["windows_s"], list) or any(
            not (isinstance(w, list) and len(w) == 2 and all(_number(x) for x in w) and w[0] <= w[1])
            for w in m["windows_s"]):
        fail("'mismatch.windows_s' must be a list of [start, end] pairs with start <= end")
    if not isinstance(m["channels"], list) or not all(isinstance(c, str) for c in m["channels"]):
        fail("'mismatch.channels' must be a list of strings")
    if not isinstance(m["markers"], list) or not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0
                                                      for i in m["markers"]):
        fail("'mismatch.markers' must be a list of non-negative integers")
    if not isinstance(doc["candidates"], list):
        fail("'candidates' must be a list")
    for i, c in enumerate(doc["candidates"]):
        if not isinstance(c, Mapping):
            fail(f"'candidates[{i}]' must be an object")
        for k in CANDIDATE_KEYS:
            if k not in c:
                fail(f"missing key 'candidates[{i}].{k}'")
        if c["effect"] not in EFFECTS:
            fail(f"'candidates[{i}].effect' = {c['effect']!r} is not in the vocabulary")
        if not _number(c["statistic"]) or not math.isfinite(c["statistic"]):
            fail(f"'candidates[{i}].statistic' must be a finite number")
        if not _number(c["p_value"]) or not 0.0 <= c["p_value"] <= 1.0:
            fail(f"'candidates[{i}].p_value' must be in [0, 1]")
    ex = doc["explained_by"]
    if not isinstance(ex, list):
        fail("'explained_by' must be a list")
    if ex == ["unexplained"]:
        pass
    elif any(e not in EFFECTS for e in ex):
        bad = next(e for e in ex if e not in EFFECTS)
        fail(f"'explained_by' holds {bad!r}: neither an effect of the vocabulary nor the lone 'unexplained'")
    if len(set(ex)) != len(ex):
        fail("'explained_by' repeats an effect")
    if ex and ex != ["unexplained"] and not m["detected"]:
        fail("'explained_by' names effects but 'mismatch.detected' is false")
    if not ex and m["detected"]:
        fail("'mismatch.detected' is true but 'explained_by' is empty (use [\"unexplained\"])")


def candidate_entries(tests: list[dict[str, Any]], decisions: Mapping[str, Any], ties: list[dict[str, Any]]
                      ) -> list[dict[str, Any]]:
    """The ``candidates`` list of the report: one entry per tested effect (its strongest test), by
    decreasing statistic, with the acceptance figures of refitted ones and unresolved ties.

    Args:
        tests: score tests (``effect``, ``channel``, ``result`` with ``statistic``/``p_value``/``dof``,
            ``p_adjusted``, ``significant``).
        decisions: effect -> acceptance record of the refitted candidates.
        ties: confusable pairs (``pair``, ``resolved``).
    """
    best: dict[str, dict] = {}
    for t in tests:
        e = t["effect"]
        if e not in best or t["result"].statistic > best[e]["result"].statistic:
            best[e] = t
    entries = []
    for e, t in sorted(best.items(), key=lambda kv: -kv[1]["result"].statistic):
        entry = {"effect": e, "statistic": float(t["result"].statistic), "p_value": float(t["p_adjusted"]),
                 "p_value_raw": float(t["result"].p_value), "channel": t["channel"], "dof": t["result"].dof,
                 "significant": t["significant"]}
        if e in decisions:
            entry.update({k: decisions[e][k] for k in ("delta_bic", "accepted", "heldout_rms_before",
                                                       "heldout_rms_after", "heldout_gain", "heldout_p", "contradicted_on")})
            if decisions[e].get("refuted_by"):
                entry["refuted_by"] = list(decisions[e]["refuted_by"])
        tie = [x["pair"] for x in ties if e in x["pair"] and not x["resolved"]]
        if tie:
            entry["tie_with"] = [p for pair in tie for p in pair if p != e]
        entries.append(entry)
    return entries
