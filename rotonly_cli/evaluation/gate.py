"""`rotonly eval`'s regression gate: limits on the comparison's numbers, so that a CI job fails
when accuracy regresses.

Absolute limits: ``--max-rotation-deg`` (the mean geodesic rotation error, the paper's metric),
``--max-position`` (the mean centre error after the similarity, GT units) and
``--min-registered`` (GT cameras with an estimated pose). A baseline (``--baseline`` an earlier
report.json, ``--tolerance`` 10 % by default): both mean errors may grow by the tolerance, the
registered cameras may not fall. Each limit is a :class:`Check`; the crossed ones make one
:class:`~rotonly_cli.errors.RegressionError` (exit code 3) whose line names each metric, its
value and its limit.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from rotonly_cli.errors import InputError, RegressionError

#: the baseline's growth allowed to the errors when --tolerance is not given
DEFAULT_TOLERANCE = 0.10

#: (name in the line, report.json path, unit) of each gated number
ROTATION = ("rotation error mean", "rotation_error_deg.mean", "deg")
POSITION = ("position error mean", "position_error.mean", "GT units")
REGISTERED = ("registered GT cameras", "num_matched", "")


@dataclass(frozen=True)
class Check:
    """One limit on one number of a report: ``value`` must stay at or below ``limit`` (``upper``)
    or at or above it; ``value`` None (a metric the comparison could not compute) fails."""

    metric: str
    unit: str
    value: float | None
    limit: float
    upper: bool
    source: str  #: what set the limit: the option, and the baseline's value

    @property
    def passed(self) -> bool:
        if self.value is None:
            return False
        if math.isclose(self.value, self.limit, rel_tol=1e-9, abs_tol=1e-12):
            return True
        return self.value <= self.limit if self.upper else self.value >= self.limit

    def line(self) -> str:
        """``rotation error mean 0.0412 deg > limit 0.03 deg (--max-rotation-deg)``."""
        unit = f" {self.unit}" if self.unit else ""
        if self.value is None:
            return f"{self.metric} not computed (see the report's notes), limit {_number(self.limit)}{unit} " \
                   f"({self.source})"
        relation = ("<=" if self.upper else ">=") if self.passed else (">" if self.upper else "<")
        return f"{self.metric} {_number(self.value)}{unit} {relation} limit {_number(self.limit)}{unit} ({self.source})"


def _number(value: float) -> str:
    return f"{value:.6g}"


def _lookup(report: dict, path: str):
    value = report
    for key in path.split("."):
        value = value.get(key) if isinstance(value, dict) else None
    return value


def parse_tolerance(text: str) -> float:
    """``"10%"`` or ``"0.1"`` -> 0.1; a bare number above 1 is refused (``10`` is written
    ``10%``). InputError (field --tolerance) otherwise."""
    raw = text.strip()
    percent = raw.endswith("%")
    try:
        value = float(raw[:-1] if percent else raw)
    except ValueError:
        raise InputError(f"{text!r} is not a share: write 10% or 0.1", field="--tolerance") from None
    if not math.isfinite(value) or value < 0:
        raise InputError(f"{text!r} is not a share >= 0", field="--tolerance")
    if not percent and value > 1:
        raise InputError(f"{text!r}: a share above 1 as a bare number; write {value:g}% for percent",
                         field="--tolerance")
    return value / 100 if percent else value


def read_baseline(path: str | Path) -> dict:
    """An earlier report.json: the file, `rotonly eval`'s -o folder, or a run's OUT (its
    eval/report.json). InputError (field --baseline) when there is none or it lacks the numbers."""
    path = Path(path)
    candidates = [path] if not path.is_dir() else [path / "report.json", path / "eval" / "report.json"]
    found = next((candidate for candidate in candidates if candidate.is_file()), None)
    if found is None:
        where = "no such file" if not path.exists() else "no report.json in it or in its eval/"
        raise InputError(f"{where} (the baseline is an earlier rotonly eval's report.json)", path=str(path),
                         field="--baseline")
    try:
        report = json.loads(found.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read as JSON: {exc}", path=str(found), field="--baseline") from None
    for _, key, _ in (ROTATION, REGISTERED):
        value = _lookup(report, key) if isinstance(report, dict) else None
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise InputError(f"no number {key} (not a rotonly eval report.json?)", path=str(found),
                             field="--baseline")
    return report


def checks(report: dict, max_rotation_deg: float | None = None, max_position: float | None = None,
           min_registered: int | None = None, baseline: dict | None = None,
           tolerance: float = DEFAULT_TOLERANCE, baseline_name: str = "--baseline") -> list[Check]:
    """The limits set on ``report`` (report.json's dict), in the order rotation, position,
    registered; absolute limits first, then the baseline's."""
    found = []

    def add(metric: tuple[str, str, str], limit: float, upper: bool, source: str) -> None:
        name, key, unit = metric
        value = _lookup(report, key)
        found.append(Check(name, unit, None if value is None else float(value), float(limit), upper, source))

    if max_rotation_deg is not None:
        add(ROTATION, max_rotation_deg, True, "--max-rotation-deg")
    if max_position is not None:
        add(POSITION, max_position, True, "--max-position")
    if min_registered is not None:
        add(REGISTERED, min_registered, False, "--min-registered")
    if baseline is not None:
        share = f"{tolerance * 100:g}%"
        for metric in (ROTATION, POSITION):
            old = _lookup(baseline, metric[1])
            if old is not None:
                add(metric, old * (1 + tolerance), True, f"{baseline_name}: {_number(old)} {metric[2]} + {share}")
        add(REGISTERED, _lookup(baseline, REGISTERED[1]), False, f"{baseline_name}: as many")
    return found


def enforce(found: list[Check]) -> None:
    """RegressionError naming every crossed limit, in one line; nothing when all held."""
    failed = [check for check in found if not check.passed]
    if failed:
        raise RegressionError("regression: " + "; ".join(check.line() for check in failed))
