"""The budget benchmark's wake-up floor: measured by a program of its own, reported beside the daemon's CPU."""

from __future__ import annotations

import math

import pytest

from robotd.bench import budget


def test_the_floor_program_runs_and_reports_a_share_of_one_core() -> None:
    share = budget.wakeup_floor(50.0, 1.0)
    assert share is not None  # the program ran and printed its CPU share
    assert math.isfinite(share)
    assert 0.0 <= share < 1.0  # one thread sleeping between wake-ups cannot take a whole core


def test_no_wake_ups_cost_nothing() -> None:
    assert budget.wakeup_floor(0.0, 1.0) == 0.0


def test_the_report_gives_the_floor_and_robotds_own_work(capsys: pytest.CaptureFixture[str]) -> None:
    rest = budget.Rates(27.0, 27.0, 114.0, "perf", 0.012, floor_cpu_share=0.005)
    driving = budget.Rates(83.0, 83.0, 693.0, "perf", 0.07, floor_cpu_share=None)
    figures = budget.report({"rest": rest, "driving": driving})
    printed = capsys.readouterr().out.splitlines()
    assert "floor 0.5%" in printed[0]
    assert "robotd's own work 0.7%" in printed[0]
    assert "could not be measured" in printed[1]
    assert figures["rest_floor_cpu_share"] == 0.005
    assert "driving_floor_cpu_share" not in figures
