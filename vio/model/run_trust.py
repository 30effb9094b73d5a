"""What the model.json beside a model (written by `vio model`) says about the run it was built from: the scale's
uncertainty from the run's factor graph, and the run's health (run.json `status` ok | degraded | failed, `reasons`).
`vio measure` refuses a model from a failed run (or one that never finished: `running`, or any status it does not
know) and flags every dimension from a degraded one; `vio compare` warns.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.errors import ModelError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunTrust:
    """What the model.json beside a model (written by `vio model`) says about the run it was built from."""

    scale_sigma_rel: float | None  # the run's relative scale sigma (1 sigma, factor graph), None when unknown
    run_status: str | None  # ok | degraded | failed (run.json's `status`), None without a run (or a model.json)
    reasons: tuple[str, ...]  # run.json's `reasons` when the run is not ok and its run.json is found
    run_dir: str | None  # the run folder model.json names
    model_warnings: tuple[str, ...]  # model.json's own `warnings` (e.g. a mesh that is not watertight)
    base_sigma_mm: float | None = None  # standard uncertainty of the base closed on the support plane, mm

    @property
    def untrusted(self) -> bool:
        """The run failed, never finished (run.json still says `running`) or has a status this code does not know."""
        return self.run_status not in (None, "ok", "degraded")

    def state(self) -> str:
        """E.g. "failed", "was degraded", "did not finish (status 'running')"."""
        if self.run_status in ("degraded", "failed"):
            return "was degraded" if self.run_status == "degraded" else "failed"
        return f"did not finish (status {self.run_status!r})"

    def why(self) -> str:
        """The run's reasons on one line."""
        return "; ".join(self.reasons) or "reasons not found"

    def warnings(self, what: str) -> tuple[str, ...]:
        """One line per reason not to trust `what` (e.g. "every dimension here") as stated: a degraded or failed
        run first, then the model's own warnings (model.json)."""
        out = [f"model.json: {w}" for w in self.model_warnings]
        if self.run_status not in (None, "ok"):
            out.insert(
                0,
                f"the run this model was built from ({self.run_dir}) {self.state()} ({self.why()}): its scale, and so "
                f"{what}, may be off by more than stated",
            )
        return tuple(out)


def run_trust_beside(model_path: Path) -> RunTrust:
    """The run's scale uncertainty and health from the model.json next to a model written by `vio model` (and the
    run.json it names, for the reasons); all empty when there is no model.json. A model.json that is not valid JSON
    is a ModelError: the scale's trust would be unknown."""
    meta_path = model_path.with_name("model.json")
    if not meta_path.is_file():
        return RunTrust(None, None, (), None, ())
    meta = _json_object(meta_path)
    sigma = meta.get("scale_sigma_rel")
    status, run_dir = meta.get("run_status"), meta.get("run")
    reasons: tuple[str, ...] = ()
    if status not in (None, "ok"):
        run_json = _run_json(model_path, run_dir)
        if run_json is None:
            log.warning("%s: the run's run.json was not found; its reasons are unknown", meta_path)
        else:
            reasons = tuple(str(r) for r in _json_object(run_json).get("reasons") or ())
    warnings = tuple(str(w) for w in meta.get("warnings") or ())
    if not isinstance(sigma, (int, float)) or not np.isfinite(sigma) or sigma < 0:
        sigma = None
    base = meta.get("base_sigma_mm")
    if not isinstance(base, (int, float)) or not np.isfinite(base) or base < 0:
        base = None
    return RunTrust(sigma, None if status is None else str(status), reasons, run_dir, warnings, base)


def _json_object(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict):
        raise ModelError(f"{path}: expected a JSON object")
    return data


def _run_json(model_path: Path, run_dir: object) -> Path | None:
    """run.json of the run model.json names (as given, or relative to the model's folder), or of OUT/run (where
    `vio model` runs `vio run` itself)."""
    candidates = [model_path.parent / "run"]
    if isinstance(run_dir, str) and run_dir:
        candidates[:0] = [Path(run_dir), model_path.parent / run_dir]
    return next((c / "run.json" for c in candidates if (c / "run.json").is_file()), None)
