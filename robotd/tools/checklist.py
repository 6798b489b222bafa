"""The doctor's findings: one line each, PASS, FAIL with the fix to apply, or SKIP with the reason."""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass


class Verdict(enum.Enum):
    """The outcome of one check."""

    PASS = "PASS"  # noqa: S105 - a verdict, not a password
    FAIL = "FAIL"
    SKIP = "SKIP"


@dataclass(frozen=True, slots=True)
class Finding:
    """One line of the checklist: what was checked, what was seen, and the fix (FAIL) or the reason (SKIP)."""

    check: str
    verdict: Verdict
    detail: str
    fix: str = ""

    def lines(self) -> list[str]:
        """The finding for a person: the verdict and what was seen, then the fix on its own line."""
        head = f"{self.verdict.value}  {self.check}: {self.detail}"
        return [head, f"      fix: {self.fix}"] if self.fix else [head]


def passed(check: str, detail: str) -> Finding:
    """A check that passed."""
    return Finding(check, Verdict.PASS, detail)


def failed(check: str, detail: str, fix: str) -> Finding:
    """A check that failed, with what to do about it."""
    return Finding(check, Verdict.FAIL, detail, fix)


def skipped(check: str, why: str) -> Finding:
    """A check that does not apply here, and why."""
    return Finding(check, Verdict.SKIP, why)


def exit_status(findings: Iterable[Finding]) -> int:
    """0 when nothing failed (skips allowed), 1 otherwise."""
    return 1 if any(f.verdict is Verdict.FAIL for f in findings) else 0


def summary(findings: list[Finding]) -> str:
    """'2 failed, 9 passed, 3 skipped'."""
    count = {verdict: sum(f.verdict is verdict for f in findings) for verdict in Verdict}
    return f"{count[Verdict.FAIL]} failed, {count[Verdict.PASS]} passed, {count[Verdict.SKIP]} skipped"
