"""The estimator's modes: the transition tables, and the path a driven robot takes through them."""

from __future__ import annotations

import dataclasses
import math
import random

import pytest

from robotd import kinematics
from robotd.config.model import EkfConfig, gated_preset, paper_preset
from robotd.estimation.estimator import Estimator
from robotd.estimation.modes import (
    HEADING_TRANSITIONS,
    POSITION_TRANSITIONS,
    REALIGNING,
    HeadingEvidence,
    HeadingMode,
    IllegalTransitionError,
    Modes,
    PositionMode,
    Verdict,
)

GEOMETRY = kinematics.Geometry()
CPR = 6800


def test_every_position_mode_answers_every_verdict_a_placed_fix_can_get() -> None:
    for mode in (PositionMode.TRACKING, PositionMode.REJECTING):
        placed = {Verdict.ACCEPTED, Verdict.GATED, Verdict.UNCONFIRMED, Verdict.RECOVERED}
        assert set(POSITION_TRANSITIONS[mode]) == placed
    assert set(POSITION_TRANSITIONS) == set(PositionMode)


@pytest.mark.parametrize(
    ("mode", "verdict"),
    [
        (PositionMode.INITIALISING, Verdict.GATED),  # nothing to gate against before a fix placed the position
        (PositionMode.INITIALISING, Verdict.RECOVERED),
        (PositionMode.TRACKING, Verdict.SEEDED),  # a placed position is never seeded again, only recovered
    ],
)
def test_a_verdict_the_mode_cannot_produce_is_a_bug(mode: PositionMode, verdict: Verdict) -> None:
    modes = Modes(heading_known=True)
    modes.position = mode
    with pytest.raises(IllegalTransitionError):
        modes.on_verdict(verdict)


def test_a_recovery_makes_the_heading_unknown_and_a_fix_too_old_changes_nothing() -> None:
    modes = Modes(heading_known=True)
    modes.on_verdict(Verdict.SEEDED)
    modes.on_evidence(HeadingEvidence.AGREES)
    assert (modes.position, modes.heading) == (PositionMode.TRACKING, HeadingMode.CONFIRMED)
    assert modes.on_verdict(Verdict.TOO_OLD) is PositionMode.TRACKING
    modes.on_verdict(Verdict.GATED)
    assert (modes.position, modes.heading) == (PositionMode.REJECTING, HeadingMode.CONFIRMED)
    modes.on_verdict(Verdict.RECOVERED)
    assert (modes.position, modes.heading) == (PositionMode.TRACKING, HeadingMode.UNKNOWN)
    assert not modes.heading_known


def test_a_confirmed_heading_is_realigned_only_when_two_windows_disagree_the_same_way() -> None:
    modes = Modes(heading_known=True)
    assert not modes.on_evidence(HeadingEvidence.AGREES)
    assert not modes.on_evidence(HeadingEvidence.DISAGREES)
    assert modes.heading.name == "SUSPECT"
    assert not modes.on_evidence(HeadingEvidence.DISAGREES)  # another direction: still a suspect
    assert modes.on_evidence(HeadingEvidence.DISAGREES_AGAIN)
    assert modes.heading.name == "CONFIRMED"
    with pytest.raises(IllegalTransitionError):
        modes.on_evidence(HeadingEvidence.WHOLE_WINDOW)  # only an unknown heading waits for a whole window


def test_the_realigning_transitions_exist_and_leave_the_heading_known() -> None:
    for mode, evidence in REALIGNING:
        assert HEADING_TRANSITIONS[mode][evidence] is not HeadingMode.UNKNOWN
    unknown, aligned = Modes(heading_known=False), Modes(heading_known=True)
    assert unknown.on_evidence(HeadingEvidence.WHOLE_WINDOW)
    assert aligned.on_evidence(HeadingEvidence.DISAGREES)  # never confirmed: the window is taken at once
    assert (unknown.heading, aligned.heading) == (HeadingMode.ALIGNED, HeadingMode.ALIGNED)


def _drive(est: Estimator, start: float, until: float, true: list[float], shift: float = 0.0) -> None:
    """Drive along the true heading true[2] at 0.3 m/s with 8 Hz fixes (3 cm noise) shifted by `shift` in x."""
    rng = random.Random(round(start * 10))
    t = start
    while t < until - 1e-9:
        t = round(t + 0.01, 6)
        true[0] += 0.3 * 0.01 * math.cos(true[2])
        true[1] += 0.3 * 0.01 * math.sin(true[2])
        est.on_twist(t, 0.3, 0.0, 0.0)
        if round(t * 100) % 12 == 0:
            est.on_fix(t, true[0] + shift + rng.gauss(0, 0.03), true[1] + rng.gauss(0, 0.03), t)


def test_a_robot_put_down_anywhere_goes_from_an_unknown_to_a_confirmed_heading_and_back_when_carried() -> None:
    est = Estimator(EkfConfig(), GEOMETRY, (0.0, 0.0), CPR)  # initial_sigma theta 3.14: unknown
    assert (est.modes.position, est.modes.heading) == (PositionMode.INITIALISING, HeadingMode.UNKNOWN)
    true = [1.0, 2.0, 2.0]
    _drive(est, 0.0, 1.0, true)
    assert (est.modes.position, est.modes.heading) == (PositionMode.TRACKING, HeadingMode.UNKNOWN)
    _drive(est, 1.0, 8.0, true)
    assert est.modes.heading is HeadingMode.CONFIRMED  # a whole window gave it, the next agreed
    assert est.counters["heading_realigned"] == 1
    _drive(est, 8.0, 11.0, true, shift=2.0)  # carried 2 m while driving on: the fixes jump
    assert est.counters["recoveries"] == 1
    assert est.modes.position is PositionMode.TRACKING
    assert est.modes.heading in (HeadingMode.UNKNOWN, HeadingMode.ALIGNED)  # in doubt again, until a whole window


def test_the_paper_preset_fuses_its_first_fix_and_never_doubts_its_heading() -> None:
    config = dataclasses.replace(EkfConfig(), initial_sigma=(1.0, 1.0, 3.14))
    paper = Estimator(paper_preset(config), GEOMETRY, (0.1, 0.0), CPR)
    assert paper.modes.heading is HeadingMode.ALIGNED  # the configured heading is taken as known
    paper.on_twist(0.0, 0.0, 0.0, 0.0)
    diagnostic = paper.on_fix(0.1, 5.0, 0.0, 0.05)
    assert diagnostic is not None
    assert diagnostic.verdict is Verdict.ACCEPTED  # no seeding: the first fix is fused like any other
    assert diagnostic.t_meas == 0.1  # fused on arrival
    assert paper.modes.position is PositionMode.TRACKING
    _drive(paper, 0.1, 10.0, [0.0, 0.0, 0.0])
    assert paper.counters["heading_realigned"] == 0
    assert paper.modes.heading is HeadingMode.ALIGNED
    assert config.gating  # the preset is a new configuration: the one it was made from is unchanged


def test_the_gated_preset_seeds_its_position_rejects_a_wild_fix_and_fuses_at_the_measurement_time() -> None:
    config = dataclasses.replace(EkfConfig(), initial_pose=(1.0, 2.0, 0.0), initial_sigma=(1.0, 1.0, 0.1))
    gated = Estimator(gated_preset(config), GEOMETRY, (0.0, 0.0), CPR, default_latency_s=0.1)
    paper = Estimator(paper_preset(config), GEOMETRY, (0.0, 0.0), CPR)
    assert gated.modes.heading is HeadingMode.ALIGNED  # like the paper's: the configured heading is known
    true = [1.0, 2.0, 0.0]
    gated.on_twist(0.0, 0.0, 0.0, 0.0)
    first = gated.on_fix(0.01, 1.0, 2.0, 0.01)
    assert first is not None
    assert first.verdict is Verdict.SEEDING  # placed by agreeing fixes (a gate alone could lock a first outlier in)
    _drive(gated, 0.0, 0.5, list(true))
    assert gated.counters["fixes_seeded"] == 1
    for est in (gated, paper):
        _drive(est, 0.5 if est is gated else 0.0, 5.0, list(true) if est is paper else true)
    wild = {}
    for name, est in (("gated", gated), ("paper", paper)):
        est.on_twist(5.01, 0.3, 0.0, 0.0)
        diagnostic = est.on_fix(5.01, 10.0, 2.0, 4.9)  # 8 m off, measured 0.11 s before it arrived
        assert diagnostic is not None
        wild[name] = diagnostic
    assert wild["gated"].verdict is Verdict.GATED
    assert wild["paper"].verdict is Verdict.ACCEPTED
    assert wild["gated"].t_meas == 4.9  # at its measurement time; the paper's filter fuses on arrival
    assert wild["paper"].t_meas == 5.01
    untimed = gated.on_fix(5.02, 2.5, 2.0, math.nan)
    assert untimed is not None
    assert untimed.t_meas == pytest.approx(5.02 - 0.1)  # the configured latency, never learnt
    assert gated.counters["calibration_windows"] == 0
