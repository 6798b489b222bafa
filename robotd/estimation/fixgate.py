"""The verdict on each IPS fix: seeding, Mahalanobis gating, lock-out recovery, and the IPS noise estimate. Pure.

- Until the position is placed, fixes are held as candidates: `seed_fixes` that agree with each other seed it (a
  first fix may be an outlier; with the heading unknown, allowing for the distance driven between them, as the
  odometry's motion cannot be removed in a direction not known). With none configured (the paper's filter), the first
  fix is judged like any other.
- Then a fix is accepted when its NIS is within the chi-square gate (2 dof), with the noise at least as configured,
  unless it is there only because the position is uncertain (`confirm_far_fixes`): a fix that would fail the gate were
  the prediction as good as a fix (as configured, or as learnt when noisier) is held (UNCONFIRMED) and fused once the
  next fix agrees with it. After an outage or a burst of outliers the gate is wide (metres after seconds without a
  fix): within it a lone outlier looks like a fix that shows the drift, and took the position 0.7 m off (a real robot's
  start with the heading unknown). Rejected fixes are remembered: when they keep coming for `recovery_min_s` and agree
  with each other once the odometry motion is removed (as innovations), the position is re-seeded on them (the robot
  was carried, or the filter drifted); one consistent burst of outliers is too short to do that.
- The IPS noise variance is estimated from the median of recent innovations, each scaled by the share of its
  predicted variance that the noise in use accounts for (r / S), up to ips_sigma_max_m^2; at least ips_sigma_m^2 (the
  configured prior) until the fixes have been judged (`trust_quieter_fixes`), at least ips_sigma_min_m^2 after:
  consecutive fixes whose errors persist agree with each other, so their innovations alone would make a correlated
  IPS look quieter than it is.
- Once the fixes are judged correlated, the noise estimate is also at least the fix noise that the judging fit saw:
  the filter follows an error that persists, so innovations see only how much it changes from fix to fix (on a real
  UWB run whose fix errors of 0.15 m persist for seconds, they put the noise at 5 mm, and the covariance with it).
- A fix that would fail the gate even with twice the noise sigma in use is an outlier, not a sample of the noise, and
  is left out of that estimate: a median is robust only while outliers are fewer than half its window, and a long
  burst of them fills it (it raised R to its ceiling, after which the gate let the burst in). Each window can still
  double the sigma, so an estimate that starts too low follows a noisier IPS.
- Why scaled, not less what the prediction accounts for (S - r, the usual covariance matching): the prediction's
  variance is itself made with the noise in use. At rest the estimate is the mean of the fixes so far, as uncertain as
  the noise assumed says, so S - r is off by as much as the assumed noise is, and the samples of the first seconds
  were biased towards the wrong side (on the flat-floor virtual robot, a 2 cm IPS configured at 3 cm was learnt as
  1.1 cm at the drive-off). The share r / S is right whichever of the two dominates S: where the fixes' averaging
  does, S and r are off by the same factor; where the odometry does, the sample is a true one whenever r is.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from typing import NamedTuple

from robotd.config.model import EkfConfig
from robotd.estimation import ekf
from robotd.estimation.heading import LN4
from robotd.estimation.modes import Modes, Verdict

Innovation3 = tuple[float, float, float]  # t_meas, innovation x, y
NOISE_SAMPLE_SPREAD = 3.0  # a fix samples the noise if it passes the gate with R + 3 R (twice the sigma) in S
NOISE_PRIOR_SAMPLES = 15  # the noise in use before the window began counts as this many samples, less those taken:
# each sample is one draw of a 2-dof chi-square, so a median of five falls below 0.4x the truth one time in ten
# (4 Hz fixes on a real robot's run: a 3 cm IPS learnt as 5 mm, one fix then turned the heading 34 degrees)


class Diagnostics(NamedTuple):
    """One fix's record: innovation nu, its covariance S (xx, xy, yy), NIS, the gate, the verdict.

    A NamedTuple: immutable, and built several times faster than a frozen dataclass (once per fix).
    """

    t: float
    t_meas: float
    nu: tuple[float, float]
    s: tuple[float, float, float]
    nis: float
    gate: float
    verdict: Verdict
    r_m: float

    @property
    def accepted(self) -> bool:
        """Whether the fix moved the estimate."""
        return self.verdict in (Verdict.ACCEPTED, Verdict.SEEDED, Verdict.RECOVERED)


class FixGate:
    """Judges fixes by their innovation; keeps the counters it owns and the IPS noise estimate."""

    def __init__(self, config: EkfConfig, counters: dict[str, int], modes: Modes) -> None:
        self.config = config
        self.counters = counters
        self.modes = modes
        self.gate = ekf.chi2_gate_2dof(config.gate_probability)
        self.r_floor = config.ips_sigma_m**2
        self.r = self.r_floor  # the IPS noise variance in use
        self.rejected: deque[Innovation3] = deque(maxlen=256)
        self.candidates: deque[Innovation3] = deque(maxlen=config.seed_fixes)
        self._candidates_travel: deque[float] = deque(maxlen=config.seed_fixes)  # the odometry's distance at each
        self._fused_travel = 0.0  # the odometry's distance at the last fix fused (judge's `travelled`)
        self.innovations: deque[float] = deque(maxlen=31)  # |nu|^2 / ln 4 x r / S, for the noise estimate
        self._ordered: list[float] = []  # the same, sorted
        self._prior = self.r  # the noise in use when the window began: its estimate leans on it until it fills

    def judge(
        self,
        t_meas: float,
        inn: ekf.Innovation,
        r: float,
        *,
        learn: bool = True,
        lower: bool = True,
        travelled: float = 0.0,
    ) -> Verdict:
        """Seed, accept, gate or recover: the fix's verdict (and the counters and noise estimate that follow; the noise
        learns from the fix only when `learn`, and only upwards unless `lower`). `travelled`: the odometry's distance
        driven at the fix, which seeding and confirming far fixes with the heading unknown need."""
        config, counters = self.config, self.counters
        if not self.modes.placed and config.seed_fixes:
            self.candidates.append((t_meas, inn.nu_x, inn.nu_y))
            self._candidates_travel.append(travelled)
            if len(self.candidates) < config.seed_fixes or not self._candidates_agree():
                return Verdict.SEEDING
            counters["fixes_seeded"] += 1
            self._fused_travel = travelled
            return Verdict.SEEDED
        if learn and config.adaptive_ips_noise and self._samples_noise(inn, r):
            self._learn_noise(inn, r, lower=lower)
        rejection = Verdict.GATED
        if not config.gating or self._inside_gate(inn, r):
            # with the heading unknown the robot may be anywhere within the distance driven since the last fix fused
            driven = 0.0 if self.modes.heading_known else abs(travelled - self._fused_travel)
            if not (config.confirm_far_fixes and self._unconfirmed(t_meas, inn, r, driven)):
                self.rejected.clear()
                counters["fixes_accepted"] += 1
                self._fused_travel = travelled
                return Verdict.ACCEPTED
            rejection = Verdict.UNCONFIRMED
        self.rejected.append((t_meas, inn.nu_x, inn.nu_y))
        if self._recoverable():
            counters["recoveries"] += 1
            self._fused_travel = travelled
            return Verdict.RECOVERED
        counters["fixes_rejected"] += 1
        return rejection

    def seed_shift(self, verdict: Verdict) -> tuple[float, float]:
        """Where a SEEDED or RECOVERED verdict moves the beacon: the median innovation of the agreeing fixes."""
        if verdict is Verdict.RECOVERED:
            recent = list(self.rejected)[-self.config.recovery_min_fixes :]
            self.forget()
        else:
            recent = list(self.candidates)
            self.candidates.clear()
            moved = max(self._candidates_travel) > min(self._candidates_travel)
            self._candidates_travel.clear()
            if moved and not self.modes.heading_known:
                # this fix's: the others' motion since is known in length only (_candidates_agree)
                return recent[-1][1], recent[-1][2]
        dx = sorted(e[1] for e in recent)[len(recent) // 2]
        dy = sorted(e[2] for e in recent)[len(recent) // 2]
        return dx, dy

    def trust_quieter_fixes(self, persistent_var: float) -> None:
        """The fixes have been judged (their correlation is known): the noise estimate may go below the configured,
        but not below `persistent_var`, the noise of fixes whose errors were found to persist (0: independent)."""
        c = self.config
        quietest = min(c.ips_sigma_min_m, c.ips_sigma_m) ** 2
        self.r_floor = min(max(quietest, persistent_var), c.ips_sigma_max_m**2)
        if c.adaptive_ips_noise:
            self.r = max(self.r, self.r_floor)

    def start_noise(self, variance: float) -> None:
        """Start the noise estimate at `variance` (what a run before learnt), within the floor and the ceiling."""
        if self.config.adaptive_ips_noise and math.isfinite(variance):
            self.r = min(max(variance, self.r_floor), self.config.ips_sigma_max_m**2)
            self._prior = self.r

    def forget(self) -> None:
        """Drop the rejected fixes and the innovations: what they were measured against is gone."""
        self.rejected.clear()
        self.innovations.clear()
        self._ordered.clear()
        self._prior = self.r

    def _agree(self, innovations: list[Innovation3]) -> bool:
        """Whether fixes (as innovations, odometry motion removed) all lie close to their median."""
        mx = sorted(e[1] for e in innovations)[len(innovations) // 2]
        my = sorted(e[2] for e in innovations)[len(innovations) // 2]
        tolerance = self._agreement()
        return all(math.hypot(e[1] - mx, e[2] - my) <= tolerance for e in innovations)

    def _candidates_agree(self) -> bool:
        """Whether the seeding candidates agree: as `_agree` with the heading known; with it unknown, each within
        the agreement of the newest plus twice the distance driven between them.

        An unplaced position moves along the initial heading's guess (robotd.estimation.history.Predictor), so with
        the heading unknown the innovations have the motion removed in a direction that may be wrong by up to pi:
        two of them differ by up to twice the distance driven between the fixes. Judged as with the heading known, a
        robot that drove off at once was never placed while it moved (2 Hz fixes of the libRSF robot: not for its
        first 12 s, until it stopped). An outlier metres away still fails, unless the robot drove metres between."""
        if self.modes.heading_known:
            return self._agree(list(self.candidates))
        newest, travel = self.candidates[-1], self._candidates_travel[-1]
        tolerance = self._agreement()
        return all(
            math.hypot(e[1] - newest[1], e[2] - newest[2]) <= tolerance + 2.0 * abs(travel - d)
            for e, d in zip(self.candidates, self._candidates_travel, strict=True)
        )

    def _agreement(self) -> float:
        """How far apart fixes of one position may lie: the configured agreement, or four sigmas of the noise."""
        return max(self.config.recovery_agreement_m, 4.0 * math.sqrt(self.r))

    def _inside_gate(self, inn: ekf.Innovation, r: float) -> bool:
        """Whether the fix passes the gate, judged with the noise at least as configured."""
        # a learnt noise below the truth (a median of few innovations can go to the floor) gated ordinary fixes of
        # a 2 cm IPS: the gate is there for outliers, which the configured noise tells apart as well
        if inn.nis <= self.gate:
            return True
        extra = self.config.ips_sigma_m**2 - r
        return (
            extra > 0.0
            and ekf.mahalanobis2(inn.nu_x, inn.nu_y, inn.s_xx + extra, inn.s_xy, inn.s_yy + extra) <= self.gate
        )

    def _unconfirmed(self, t_meas: float, inn: ekf.Innovation, r: float, driven: float) -> bool:
        """Whether a fix inside the gate is beyond it, by more than `driven` metres, for a prediction as good as a fix
        (S = 2r, r at least the configured ips_sigma_m^2), and the fix before it (the newest rejected one) does not
        agree with it.

        `driven`: how far the robot drove, in a direction not known (the heading unknown), since the last fix fused.
        Without it, 2 Hz fixes of the libRSF robot driving off at 0.4 m/s were held every other one (each 0.2 m
        from a position that could not follow the motion) and the error reached 0.4 m."""
        # the configured noise as a floor: a learnt r below the true noise (a conservative P leaves less of the
        # innovations to the fixes) would hold ordinary fixes
        distance = math.hypot(inn.nu_x, inn.nu_y) - driven
        if distance <= 0.0 or distance * distance <= 2.0 * max(r, self.config.ips_sigma_m**2) * self.gate:
            return False
        return not (self.rejected and self._agree([self.rejected[-1], (t_meas, inn.nu_x, inn.nu_y)]))

    def _recoverable(self) -> bool:
        """Rejections persisted long enough, and the latest of them agree with each other."""
        c = self.config
        rejected = self.rejected
        if len(rejected) < c.recovery_min_fixes or rejected[-1][0] - rejected[0][0] < c.recovery_min_s:
            return False
        # the rejected fixes of the last recovery_min_s, as innovations (odometry motion removed)
        newest = rejected[-1][0]
        recent = [e for e in rejected if newest - e[0] <= c.recovery_min_s]
        return len(recent) >= c.recovery_min_fixes and self._agree(recent)

    def _samples_noise(self, inn: ekf.Innovation, r: float) -> bool:
        """Whether the fix is within the gate of a noise twice as large in sigma as r: a sample of the noise."""
        extra = NOISE_SAMPLE_SPREAD * r
        return ekf.mahalanobis2(inn.nu_x, inn.nu_y, inn.s_xx + extra, inn.s_xy, inn.s_yy + extra) <= self.gate

    def _learn_noise(self, inn: ekf.Innovation, r: float, *, lower: bool = True) -> None:
        """Track the IPS noise variance as the median innovation, scaled by the share r / S of its variance that the
        noise accounts for (module docstring), with the noise in use before the window began counting as the samples
        it still lacks (NOISE_PRIOR_SAMPLES); not below the noise in use unless `lower` (a prediction wider than the
        truth makes the median a lower bound)."""
        s = 0.5 * (inn.s_xx + inn.s_yy)  # per axis
        value = (inn.nu_x * inn.nu_x + inn.nu_y * inn.nu_y) / LN4 * (r / s)
        window, ordered = self.innovations, self._ordered
        if len(window) == window.maxlen:
            del ordered[bisect.bisect_left(ordered, window[0])]
        window.append(value)
        bisect.insort(ordered, value)  # the window kept sorted too: its median without sorting it at every fix
        if len(ordered) >= 5:
            learnt = min(max(self._median_with_prior(), self.r_floor), self.config.ips_sigma_max_m**2)
            self.r = learnt if lower else max(learnt, self.r)

    def _median_with_prior(self) -> float:
        """The median of the window's samples and, for each sample it lacks of NOISE_PRIOR_SAMPLES, one at the prior."""
        ordered, prior = self._ordered, self._prior
        lacking = max(NOISE_PRIOR_SAMPLES - len(ordered), 0)
        middle = (len(ordered) + lacking) // 2
        below = bisect.bisect_left(ordered, prior)  # the prior's copies sit between ordered[:below] and the rest
        if middle < below:
            return ordered[middle]
        if middle < below + lacking:
            return prior
        return ordered[middle - lacking]


__all__ = ["Diagnostics", "FixGate", "Verdict"]
