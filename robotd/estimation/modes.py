"""The estimator's modes and their transitions, as tables: where the position and the heading stand. Pure.

Position, moved by each fix's verdict (robotd.estimation.fixgate):

    INITIALISING --SEEDED, ACCEPTED--> TRACKING --GATED--> REJECTING --ACCEPTED, RECOVERED--> TRACKING

  INITIALISING until agreeing fixes seed the position (or, with no seeding configured, until the first fix is fused);
  a fix beyond the gate makes it REJECTING; an accepted fix, or rejected fixes that agreed long enough (RECOVERED,
  the position re-seeded on them), make it TRACKING again.

Heading, moved by each trustworthy rotation fit of a window of travel (robotd.estimation.heading), * marking the
transitions that take the window's heading:

    UNKNOWN   --WHOLE_WINDOW*-->    ALIGNED
    ALIGNED   --AGREES-->           CONFIRMED     ALIGNED   --DISAGREES*-->      ALIGNED
    CONFIRMED --AGREES-->           CONFIRMED     CONFIRMED --DISAGREES-->       SUSPECT
    SUSPECT   --AGREES-->           CONFIRMED     SUSPECT   --DISAGREES-->       SUSPECT
    SUSPECT   --DISAGREES_AGAIN*--> CONFIRMED
    any       --RECOVERED (a fix's verdict)-->    UNKNOWN
    any       --LOST (odometry paused)-->         UNKNOWN

  UNKNOWN at start when the configured initial heading is uncertain, after every recovery (a robot carried off may
  have been turned), and after a pause in the odometry long enough to have turned the robot by more than an unknown
  heading's sigma (robotd.estimation.estimator): the position then follows the fixes, and the first trustworthy fit of
  a whole window gives the heading. ALIGNED: known, but no window has agreed with it yet; a window that disagrees is
  taken at once. CONFIRMED: a window agreed. SUSPECT: after that, one window disagreed (an echo can bend one window);
  the next decides, and is taken only if it disagrees the same way.
"""

from __future__ import annotations

import enum


class Verdict(enum.Enum):
    """What happened to one fix: the events of the position's modes."""

    ACCEPTED = "accepted"
    SEEDED = "seeded"  # the first agreeing fixes set the position
    SEEDING = "seeding"  # held until enough fixes agree (a first fix may be an outlier)
    RECOVERED = "recovered"  # rejected fixes agreed long enough: the position was re-seeded
    GATED = "gated"  # rejected: NIS beyond the gate
    UNCONFIRMED = "unconfirmed"  # inside a gate made wide by an uncertain position, far from it: the next fix decides
    TOO_OLD = "too_old"  # measured before the history's start


class PositionMode(enum.Enum):
    """Where the position stands with respect to the fixes (the value is the pose stream's `fix_state`)."""

    INITIALISING = "initialising"  # no fix placed the position yet
    TRACKING = "tracking"  # the latest fix was accepted
    REJECTING = "rejecting"  # fixes arrive but are gated out; recovery watches them


class HeadingMode(enum.Enum):
    """What driving has shown about the heading."""

    UNKNOWN = "unknown"  # the position follows the fixes until a whole window of travel gives the heading
    ALIGNED = "aligned"  # known (configured, or taken from a window), not yet confirmed by one
    CONFIRMED = "confirmed"  # a window's fit agreed with the filter
    SUSPECT = "suspect"  # confirmed, then one window disagreed: the next one decides


class HeadingEvidence(enum.Enum):
    """What one trustworthy rotation fit of a window of travel says about the filter's heading."""

    WHOLE_WINDOW = "whole_window"  # a whole window's fit while the heading is unknown
    AGREES = "agrees"  # within three standard deviations of the filter's heading
    DISAGREES = "disagrees"  # beyond four (and beyond the smallest re-alignment worth making)
    DISAGREES_AGAIN = "disagrees_again"  # the window after a disagreeing one disagrees the same way


P, H, V, E = PositionMode, HeadingMode, Verdict, HeadingEvidence

POSITION_TRANSITIONS: dict[PositionMode, dict[Verdict, PositionMode]] = {
    P.INITIALISING: {V.SEEDING: P.INITIALISING, V.SEEDED: P.TRACKING, V.ACCEPTED: P.TRACKING},
    P.TRACKING: {V.ACCEPTED: P.TRACKING, V.GATED: P.REJECTING, V.UNCONFIRMED: P.REJECTING, V.RECOVERED: P.TRACKING},
    P.REJECTING: {V.ACCEPTED: P.TRACKING, V.GATED: P.REJECTING, V.UNCONFIRMED: P.REJECTING, V.RECOVERED: P.TRACKING},
}
"""The position mode after a fix's verdict (a fix too old to place changes nothing)."""

HEADING_TRANSITIONS: dict[HeadingMode, dict[HeadingEvidence, HeadingMode]] = {
    H.UNKNOWN: {E.WHOLE_WINDOW: H.ALIGNED},
    H.ALIGNED: {E.AGREES: H.CONFIRMED, E.DISAGREES: H.ALIGNED},
    H.CONFIRMED: {E.AGREES: H.CONFIRMED, E.DISAGREES: H.SUSPECT},
    H.SUSPECT: {E.AGREES: H.CONFIRMED, E.DISAGREES: H.SUSPECT, E.DISAGREES_AGAIN: H.CONFIRMED},
}
"""The heading mode after a window's evidence."""

REALIGNING: frozenset[tuple[HeadingMode, HeadingEvidence]] = frozenset(
    {(H.UNKNOWN, E.WHOLE_WINDOW), (H.ALIGNED, E.DISAGREES), (H.SUSPECT, E.DISAGREES_AGAIN)}
)
"""The transitions that take the window's heading (the estimator re-aligns its state on it)."""


class IllegalTransitionError(RuntimeError):
    """An event the current mode has no transition for: a bug in the estimator, never bad input."""


class Modes:
    """The estimator's position and heading modes, changed only through the tables above."""

    # placed and heading_known are read at every odometry sample: kept as attributes, set with the modes they follow
    __slots__ = ("_heading", "_position", "heading_known", "placed")

    def __init__(self, *, heading_known: bool) -> None:
        self.position = PositionMode.INITIALISING
        self.heading = HeadingMode.ALIGNED if heading_known else HeadingMode.UNKNOWN

    @property
    def position(self) -> PositionMode:
        """The position mode."""
        return self._position

    @position.setter
    def position(self, mode: PositionMode) -> None:
        self._position = mode
        self.placed: bool = mode is not PositionMode.INITIALISING  # whether a fix has placed the position

    @property
    def heading(self) -> HeadingMode:
        """The heading mode."""
        return self._heading

    @heading.setter
    def heading(self, mode: HeadingMode) -> None:
        self._heading = mode
        self.heading_known: bool = mode is not HeadingMode.UNKNOWN  # in any mode but UNKNOWN

    def on_verdict(self, verdict: Verdict) -> PositionMode:
        """Take a fix's verdict; returns the previous position mode. A recovery makes the heading unknown."""
        before = self.position
        if verdict is Verdict.TOO_OLD:
            return before
        try:
            self.position = POSITION_TRANSITIONS[before][verdict]
        except KeyError:
            raise IllegalTransitionError(f"no transition from position {before.name} on {verdict.name}") from None
        if verdict is Verdict.RECOVERED:
            self.heading = HeadingMode.UNKNOWN
        return before

    def lose_heading(self) -> None:
        """The odometry paused for long enough that the heading may be anything: it is unknown again."""
        self.heading = HeadingMode.UNKNOWN

    def on_evidence(self, evidence: HeadingEvidence) -> bool:
        """Take a window's evidence about the heading; returns whether the window's heading is to be taken."""
        before = self.heading
        try:
            self.heading = HEADING_TRANSITIONS[before][evidence]
        except KeyError:
            raise IllegalTransitionError(f"no transition from heading {before.name} on {evidence.name}") from None
        return (before, evidence) in REALIGNING


__all__ = [
    "HEADING_TRANSITIONS",
    "POSITION_TRANSITIONS",
    "REALIGNING",
    "HeadingEvidence",
    "HeadingMode",
    "IllegalTransitionError",
    "Modes",
    "PositionMode",
    "Verdict",
]
