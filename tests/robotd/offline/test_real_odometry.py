"""A real robot's wheel odometry (the libRSF dataset) with Marvelmind-like fixes simulated on its ground truth, as the
logs robotd is judged on are made: the robot starts facing a direction the filter is not told."""

from __future__ import annotations

import pytest
from paths import LIBRSF

from robotd.config.model import parse
from robotd.logs.sensorlog import Event, Meta
from robotd.offline import librsf
from robotd.offline.experiment import through_log_format
from robotd.offline.metrics import ErrorStats
from robotd.offline.replay import replay
from robotd.sim.ips import IpsParams
from robotd.sim.refix import refixed

pytestmark = pytest.mark.skipif(not LIBRSF.is_dir(), reason="the shared libRSF dataset is not beside the repository")


def _with_simulated_fixes(seed: int) -> tuple[Meta, list[Event]]:
    """The dataset's odometry and truth, its UWB fixes replaced by the virtual hedgehog's measuring the truth (12 Hz,
    2 cm noise, 50-150 ms latency, measurement times stated, no outliers), as `robotd simulate-fixes --kind clean`."""
    meta, events = librsf.convert(LIBRSF)
    params = IpsParams(noise_m=0.02)
    return meta, refixed(events, params, "clean", seed, (0.0, 0.0))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_robot_starting_in_an_untold_direction_is_tracked_better_than_by_its_fixes(seed: int) -> None:
    meta, events = _with_simulated_fixes(seed)
    result = replay(through_log_format(meta, events), parse(""))  # the defaults: the heading unknown at power-on
    assert result.metrics is not None
    ours, fixes = result.metrics["ekf"], result.metrics["ips"]
    assert isinstance(ours, ErrorStats)
    assert isinstance(fixes, ErrorStats)
    assert result.counters["heading_realigned"] >= 1
    # the robot drives off facing about 180 degrees from the filter's guess: moving the position along the guess
    # until the heading is aligned put it up to 0.2 m off (2-3x the fixes' largest error, RMSE above theirs)
    assert ours.rmse_m < fixes.rmse_m
    assert ours.max_m < 2.0 * fixes.max_m
