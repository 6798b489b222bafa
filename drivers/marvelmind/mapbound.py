"""Where fixes may be: the map's bounds, from the configuration or from the stationary beacons the hedgehog reports.

Theory of operation. A hedgehog moves among its stationary beacons: a fix far outside them is a fault (a wrong
solution of the trilateration, a corrupted frame, another map's coordinates), and fused, a filter that has been
rejecting fixes for a while re-seeds its pose on it. Configured bounds `[xmin, ymin, xmax, ymax]` are used as they
are; without them, the bounding box of the latest stationary beacons' frame (codes 0x0002, 0x0012: the map as the
modem knows it, beacons flagged not applicable left out), grown by a margin on every side, once it holds at least two
distinct beacons. Before any such frame there is no bound. Sans-I/O: events in, a verdict out.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.marvelmind.events import StationaryBeacons

Box = tuple[float, float, float, float]  # xmin, ymin, xmax, ymax (m)


class MapBound:
    """Whether a fix (x, y) lies inside the map."""

    def __init__(self, bounds_m: Sequence[float] = (), margin_m: float = 3.0) -> None:
        if len(bounds_m) not in (0, 4):
            raise ValueError(f"bounds must be [xmin, ymin, xmax, ymax] or empty, got {list(bounds_m)}")
        self.configured: Box | None = None
        if bounds_m:
            xmin, ymin, xmax, ymax = (float(v) for v in bounds_m)
            if not (xmin < xmax and ymin < ymax):
                raise ValueError(f"bounds must have xmin < xmax and ymin < ymax, got {list(bounds_m)}")
            self.configured = (xmin, ymin, xmax, ymax)
        self.margin_m = margin_m
        self._beacons_box: Box | None = None

    @property
    def box(self) -> Box | None:
        """The bounds fixes are held to now, or None while there are none."""
        return self.configured if self.configured is not None else self._beacons_box

    def on_beacons(self, event: StationaryBeacons) -> None:
        """A stationary beacons' frame: the map as it is now (a frame of fewer than two distinct beacons is kept
        out: it cannot span a map)."""
        positions = {(b.x, b.y) for b in event.beacons if b.applicable}
        if len(positions) < 2:
            return
        xs, ys = [x for x, _ in positions], [y for _, y in positions]
        m = self.margin_m
        self._beacons_box = (min(xs) - m, min(ys) - m, max(xs) + m, max(ys) + m)

    def admits(self, x: float, y: float) -> bool:
        """Whether (x, y) is inside the bounds (always, while there are none)."""
        box = self.box
        if box is None:
            return True
        xmin, ymin, xmax, ymax = box
        return xmin <= x <= xmax and ymin <= y <= ymax
