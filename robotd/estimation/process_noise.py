"""The process noise learnt from the fixes: one scale on the configured odometry noise, from the innovations' whiteness.

Theory of operation: the configured odometry noise (`odom_*_sigma_m`, `*_heading_sigma_rad`) is a prior for a typical
floor; a robot on a flat, grippy floor drifts far less, one on a rough floor more. The innovations' sizes cannot tell
which, since the IPS noise estimate (robotd.estimation.fixgate) absorbs whatever the prediction leaves over. Their
*sequence* can (Mehra's whiteness test): with the right gain the innovations of consecutive fixes are uncorrelated;
a process noise too large makes the filter chase each fix's noise, so the next innovation undoes the last (negative
correlation); one too small lets odometry drift go unfollowed, so innovations persist (positive correlation). Each
innovation is paired with every one of the SPAN_S before it: odometry drift is slow (a floor, a traction bias), and a
filter that trusts odometry more corrects it more slowly, so short lags alone would miss it and keep lowering the
scale. The scale moves in log space by a small step times the summed correlation, bounded, and so settles where the
innovations are white. Fix errors that persist on their own (multipath, judged by the calibration's windows) also
make innovations persist whatever the gain: the scale then goes back to its prior, for it cannot be told from them.
The step itself adapts (Kesten's rule): it starts large, so that a wrong prior is left within about 30 s, and shrinks
each time the summed correlation of a block of updates changes sign, for the scale then oscillates about where the
innovations are white; blocks that agree in sign several times running grow it back (the floor changed).
Pure.
"""

from __future__ import annotations

import math
from collections import deque

STEP = 0.03  # log-scale change per unit of summed correlation while the scale is leaving its prior: it settles
# within about 30 s of driving (on the flat-floor virtual robot it is a tenth of the prior by then; 0.006 was still
# at 0.4 after 47 s). Symmetric: the sum is heavy-tailed, and unequal steps up and down ran the scale to its upper
# bound on white innovations
STEP_SETTLED = 0.006  # the smallest step, reached once the sign keeps changing: held at STEP, the scale's log spread
# by 0.9-1.0 over minutes of config/sim.yaml's square and touched both bounds; 0.006 alone kept it within 0.3
BLOCK = 24  # learning updates per block whose summed correlation's sign is watched (2 s of fixes at 12 Hz)
SHRINK = 0.8  # the step's factor at a change of sign, and its inverse after GROW_AFTER blocks of one sign: on white
GROW_AFTER = 4  # innovations a change comes every other block and such a run every eighth, so the step shrinks to
# STEP_SETTLED within about a minute, while a scale leaving its prior sees one sign and keeps STEP
LAGS = 128  # each new innovation is paired with at most this many before it, within SPAN_S
SPAN_S = 8.0  # short lags see the fixes' noise chased, long ones the odometry's drift left unfollowed: both count
MIN_MOTION_M = 0.005  # no pair when the robot hardly moved since the fix before: at rest the odometry adds no noise
MIN_TURN_RAD = 0.02
CLIP = 3.0  # normalised innovations are clipped to this size: one wild fix cannot throw the scale


class ProcessNoiseScale:
    """The multiplier of the configured odometry noise variances, within [low, high] (low <= 1 <= high, as the
    configuration requires), learnt from accepted fixes; `start` (bounded) until learnt: 1, the configuration itself,
    or what a run before learnt."""

    def __init__(self, low: float, high: float, start: float = 1.0) -> None:
        self.low = low
        self.high = high
        self.value = min(max(start, low), high) if math.isfinite(start) else 1.0
        self.step = STEP  # the log-scale change per unit of summed correlation (Kesten's rule, see the docstring)
        self._block = (0, 0.0)  # learning updates in the current block, and their summed correlation
        self._sign = 0.0  # of the last whole block's summed correlation (0: none yet)
        self._run = 0  # blocks of that sign in a row
        self.pairs = 0  # pairs of innovations learnt from
        self._window: deque[tuple[float, float, float, float]] = deque()  # t, wx, wy, |w|^2 of the last SPAN_S
        self._sum = (0.0, 0.0, 0.0)  # of wx, wy, |w|^2 over the window: each new innovation costs O(1)
        self._odometry = (math.nan, math.nan)  # distance travelled and heading at the newest innovation

    def reset(self) -> bool:
        """Back to the prior, 1, forgetting the innovations; returns whether the scale changed."""
        changed = self.value != 1.0
        self.value = 1.0
        self.step, self._block, self._sign, self._run = STEP, (0, 0.0), 0.0, 0
        self.forget()
        return changed

    def forget(self) -> None:
        """The next innovation starts no pair (a seed, a recovery or a rejected fix came between)."""
        self._window.clear()
        self._sum = (0.0, 0.0, 0.0)

    def on_innovation(
        self, t: float, nu: tuple[float, float], s: float, odometry: tuple[float, float], *, learn: bool
    ) -> bool:
        """An accepted fix's innovation nu of predicted per-axis variance s, measured at t with the odometry's
        (distance travelled, heading) then; learn only when `learn` (fixes judged independent, heading known).
        Returns whether the scale changed."""
        if s <= 0.0:
            return False
        inv = 1.0 / math.sqrt(s)
        wx, wy = nu[0] * inv, nu[1] * inv
        energy = wx * wx + wy * wy
        if energy > CLIP * CLIP:
            shrink = CLIP / math.sqrt(energy)
            wx, wy, energy = wx * shrink, wy * shrink, CLIP * CLIP
        window = self._window
        sx, sy, se = self._sum
        while window and (t - window[0][0] > SPAN_S or len(window) >= LAGS):
            old = window.popleft()
            sx, sy, se = sx - old[1], sy - old[2], se - old[3]
        if not window:
            sx = sy = se = 0.0  # no rounding carried from one run of pairs to the next
        dist, heading = odometry
        moved = dist - self._odometry[0] >= MIN_MOTION_M or abs(heading - self._odometry[1]) >= MIN_TURN_RAD
        self._odometry = odometry
        changed = False
        if learn and moved and window and t > window[-1][0]:
            # the summed correlation of this innovation with each one of the window, over their mean size
            mean_energy = (se + energy) / (len(window) + 1)
            if mean_energy > 0.0:
                correlation = (wx * sx + wy * sy) / mean_energy
                self.pairs += len(window)
                value = min(max(self.value * math.exp(self.step * correlation), self.low), self.high)
                self._adapt_step(correlation)
                changed = value != self.value
                self.value = value
        window.append((t, wx, wy, energy))
        self._sum = (sx + wx, sy + wy, se + energy)
        return changed

    def _adapt_step(self, correlation: float) -> None:
        """Count one update's correlation into the block; at the block's end, shrink the step on a change of sign
        and grow it back after GROW_AFTER blocks of one sign."""
        n, total = self._block[0] + 1, self._block[1] + correlation
        if n < BLOCK:
            self._block = (n, total)
            return
        self._block = (0, 0.0)
        sign = math.copysign(1.0, total)
        if self._sign not in (0.0, sign):
            self.step = max(self.step * SHRINK, STEP_SETTLED)
            self._run = 1
        else:
            self._run += 1
            if self._run >= GROW_AFTER:
                self.step = min(self.step / SHRINK, STEP)
        self._sign = sign


__all__ = ["ProcessNoiseScale"]
