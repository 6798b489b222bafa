"""What `robotd scorecard` writes: scorecard.md (the verdicts, then a row per log), summary.md and scorecard.json.

Like the experiment's results, the outputs depend only on the card (no dates, no timings), so `make docs` regenerates
the same files from the same code and configuration.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from robotd.offline.experiment import BASELINE_MARGIN
from robotd.offline.metrics import ErrorStats
from robotd.offline.replay import BASELINES
from robotd.offline.scorecard import (
    GEOMETRY_RMSE_RATIO,
    INSIDE_95_MIN,
    LATENCY_TOLERANCE_S,
    NEES_RANGE,
    CalibrationCheck,
    Entry,
    Scorecard,
)

NO_VALUE = "–"
MET, MISSED = "met", "**missed**"


def _best_baseline(entry: Entry) -> tuple[ErrorStats, ErrorStats] | None:
    """The baseline with the smallest RMSE and the one with the smallest maximum (None without baselines)."""
    stats = [s for name in BASELINES if (s := entry.run.metrics.get(name)) is not None]
    if not stats:
        return None
    return min(stats, key=lambda s: s.rmse_m), min(stats, key=lambda s: s.max_m)


def _figure(value: float | None, digits: int) -> str:
    return NO_VALUE if value is None else f"{value:.{digits}f}"


def _row(entry: Entry) -> str:
    ours = entry.run.metrics.get("ekf")
    best = _best_baseline(entry)
    honesty = entry.run.consistency.get("ekf")
    cells = [
        entry.family,
        str(entry.seed),
        _figure(None if ours is None else ours.rmse_m, 4),
        _figure(None if best is None else best[0].rmse_m, 4),
        _figure(None if ours is None else ours.max_m, 3),
        _figure(entry.run.ekf_worst_at_s, 1),
        _figure(None if best is None else best[1].max_m, 3),
        _figure(None if honesty is None else honesty.inside_95, 2),
        _figure(None if honesty is None else honesty.nees_mean, 2),
        MISSED if entry.run.baseline_misses() else MET,
        MISSED if entry.honesty_misses() else MET,
    ]
    return "| " + " | ".join(cells) + " |"


def _count(what: str, failing: list[str], total: int) -> str:
    missed = f" (missed: {', '.join(failing)})" if failing else ""
    return f"{what}: met on {total - len(failing)} of {total}{missed}."


def _name(entry: Entry) -> str:
    return f"{entry.family} {entry.seed}"


def _check_line(check: CalibrationCheck) -> str:
    unit = f"{check.measured * 1e3:.1f} ms" if check.target == "latency" else f"{check.measured:.2f} x"
    return f"| {check.target} | {check.seed} | {unit} | {MET if check.met else MISSED} | {check.detail} |"


def markdown(card: Scorecard, *, rows: bool = True) -> str:
    """The card as Markdown: the verdicts over all logs (naming the logs that miss), the calibration checks, then
    every log's row unless `rows` is False (the README's copy)."""
    seeds = ", ".join(map(str, card.seeds))
    low, high = NEES_RANGE
    entries = card.entries
    lines = [
        f"#### Scorecard: `{card.config_name}`, {len(entries)} logs (seeds {seeds}, {card.loops} loop(s) each)",
        "",
        (
            "Every scenario and variant of the virtual robot"
            + (
                " (`heading` put down facing any way, its filter told nothing of the heading)"
                if any(e.family == "heading" for e in entries)
                else ""
            )
            + (
                ", and the libRSF robot's real odometry and truth with the virtual hedgehog's clean, untimed and harsh "
                "fixes (replayed with the default filter),"
                if any(e.family.startswith("libRSF") for e in entries)
                else ","
            )
            + " checked one by one against the issue's targets (`robotd/offline/scorecard.py`)."
        ),
        "",
        "- "
        + _count(
            f"Against the baselines (RMSE at most {BASELINE_MARGIN:g} x the best of the raw fixes, the paper's EKF and "
            "the gated EKF, and a max no larger than the smallest of theirs)",
            [_name(e) for e in entries if e.run.baseline_misses()],
            len(entries),
        ),
        "- "
        + _count(
            f"Honest (truth inside its own 95 % ellipse at least {INSIDE_95_MIN:g} of the time, mean NEES within "
            f"[{low:g}, {high:g}])",
            [_name(e) for e in entries if e.honesty_misses()],
            len(entries),
        ),
    ]
    for target, text in (
        ("latency", f"Delay of untimed fixes learnt within {LATENCY_TOLERANCE_S * 1e3:.0f} ms after 30 s of driving"),
        (
            "geometry",
            (
                f"A robot configured up to 12 % off: RMSE after 30 s of driving within {GEOMETRY_RMSE_RATIO:g} x "
                "that of the same log told its true geometry"
            ),
        ),
    ):
        checks = [c for c in card.checks if c.target == target]
        if checks:
            lines.append("- " + _count(text, [f"seed {c.seed}" for c in checks if not c.met], len(checks)))
    lines += ["", card.librsf_note, ""]
    if card.checks:
        lines += ["| calibration target | seed | measured | verdict | detail |", "|---|--:|--:|---|---|"]
        lines += [_check_line(check) for check in card.checks]
        lines.append("")
    if not rows:
        return "\n".join(lines).rstrip() + "\n"
    lines += [
        (
            "| log | seed | RMSE (m) | best baseline RMSE (m) | max (m) | max at (s) | smallest baseline max (m) "
            "| inside 95 % | mean NEES | against the baselines | honest |"
        ),
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|---|---|",
    ]
    lines += [_row(entry) for entry in entries]
    return "\n".join(lines) + "\n"


def as_json(card: Scorecard) -> dict[str, Any]:
    """The card as plain data: every log's scores and misses, every calibration check."""
    logs = []
    for entry in card.entries:
        ours = entry.run.metrics.get("ekf")
        honesty = entry.run.consistency.get("ekf")
        logs.append(
            {
                "family": entry.family,
                "seed": entry.seed,
                "ekf": None if ours is None else ours.as_dict(),
                "ekf_worst_at_s": None if entry.run.ekf_worst_at_s is None else round(entry.run.ekf_worst_at_s, 3),
                "consistency": None if honesty is None else honesty.as_dict(),
                "baseline_misses": entry.run.baseline_misses(),
                "honesty_misses": entry.honesty_misses(),
            }
        )
    checks = [
        {
            "target": c.target,
            "seed": c.seed,
            "measured": round(c.measured, 6),
            "allowed": c.allowed,
            "met": c.met,
            "detail": c.detail,
        }
        for c in card.checks
    ]
    return {
        "config": card.config_name,
        "seeds": list(card.seeds),
        "loops": card.loops,
        "logs": logs,
        "calibration_checks": checks,
        "librsf": card.librsf_note,
    }


def write_scorecard(card: Scorecard, out: Path) -> list[Path]:
    """Write scorecard.md (every row), summary.md (without them: the README's copy) and scorecard.json into `out`;
    the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    md, summary, js = out / "scorecard.md", out / "summary.md", out / "scorecard.json"
    md.write_text(markdown(card), encoding="utf-8")
    summary.write_text(markdown(card, rows=False), encoding="utf-8")
    js.write_text(json.dumps(as_json(card), indent=1) + "\n", encoding="utf-8")
    return [md, summary, js]


__all__ = ["as_json", "markdown", "write_scorecard"]
