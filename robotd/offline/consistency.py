"""Whether a filter tells the truth about its uncertainty: NEES against ground truth, NIS of its fixes.

NEES (normalised estimation error squared) of a position estimate is e^T P^-1 e, e the error against truth and P the
2x2 position block of the estimate's own covariance: for an honest filter it is chi-square with 2 degrees of freedom,
mean 2, and at most 5.991 (the 95 % ellipse) 95 % of the time. NIS is the same for each accepted fix's innovation
against its predicted covariance S. A filter that claims less uncertainty than it has shows a mean NEES above 2 and
a share inside its 95 % ellipse below 0.95; one that claims more, the opposite. Estimates outside the truth's span
are not scored.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robotd.estimation.ekf import Cov
from robotd.estimation.fixgate import Diagnostics
from robotd.estimation.modes import Verdict
from robotd.offline.metrics import Trajectory

FloatArray = npt.NDArray[np.float64]

CHI2_2DOF_95 = 5.991464547107979  # -2 ln(0.05): the 95 % quantile of a chi-square with 2 dof


@dataclass(frozen=True, slots=True)
class Consistency:
    """NEES of the position against truth and NIS of the judged fixes (None where there was nothing to score)."""

    nees_mean: float | None
    nees_median: float | None
    inside_95: float | None  # share of estimates whose true position lies inside their own 95 % ellipse
    nis_mean: float | None  # of the fixes the filter accepted (a gated outlier's NIS says nothing of its honesty)
    nis_within_95: float | None  # share of those whose NIS is below the 95 % quantile
    fixes_accepted: int

    def as_dict(self) -> dict[str, float | int | None]:
        """The metrics.json entry."""

        def rounded(value: float | None) -> float | None:
            return None if value is None else round(value, 4)

        return {
            "nees_mean": rounded(self.nees_mean),
            "nees_median": rounded(self.nees_median),
            "inside_95": rounded(self.inside_95),
            "nis_mean": rounded(self.nis_mean),
            "nis_within_95": rounded(self.nis_within_95),
            "fixes_accepted": self.fixes_accepted,
        }


def position_nees(truth: Trajectory, estimates: Trajectory, covariances: Sequence[Cov] | FloatArray) -> np.ndarray:
    """Each estimate's position NEES against truth (estimates outside the truth's span left out); covariances: P's
    upper triangle of each estimate."""
    if len(estimates) == 0 or len(truth) == 0:
        return np.zeros(0)
    tx, ty, _, inside = truth.at(estimates.t)
    p = np.asarray(covariances, dtype=np.float64).reshape(-1, 6)[inside]
    ex = (estimates.x - tx)[inside]
    ey = (estimates.y - ty)[inside]
    xx, xy, yy = p[:, 0], p[:, 1], p[:, 3]
    det = xx * yy - xy * xy
    ok = det > 0.0
    nees: np.ndarray = (ex * ex * yy - 2.0 * ex * ey * xy + ey * ey * xx)[ok] / det[ok]
    return nees


def consistency(
    truth: Trajectory | None,
    estimates: Trajectory,
    covariances: Sequence[Cov] | FloatArray,
    diagnostics: Sequence[Diagnostics],
) -> Consistency:
    """NEES statistics (when there is truth) and NIS statistics of a filter's run."""
    nees = position_nees(truth, estimates, covariances) if truth is not None else np.zeros(0)
    judged = np.array([d.nis for d in diagnostics if d.verdict is Verdict.ACCEPTED], dtype=np.float64)
    return Consistency(
        nees_mean=float(np.mean(nees)) if len(nees) else None,
        nees_median=float(np.median(nees)) if len(nees) else None,
        inside_95=float(np.mean(nees <= CHI2_2DOF_95)) if len(nees) else None,
        nis_mean=float(np.mean(judged)) if len(judged) else None,
        nis_within_95=float(np.mean(judged <= CHI2_2DOF_95)) if len(judged) else None,
        fixes_accepted=len(judged),
    )


__all__ = ["CHI2_2DOF_95", "Consistency", "consistency", "position_nees"]
