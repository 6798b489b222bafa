"""Foxglove messages for what robotd knows, built from plain data: poses, trails, the covariance ellipse, fixes
coloured by the gate's verdict, the stationary beacons, the frame tree. Pure: no channel, no I/O.

Frames are REP-103 (x forward, y left, z up, angles counter-clockwise) and REP-105's names: `map` (the Marvelmind map),
`odom`, `base_link` (the robot's centre), `beacon` (the hedgehog on the robot). See robotd.viz.frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from foxglove.messages import (
    Color,
    Duration,
    FrameTransform,
    FrameTransforms,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Odometry,
    Point3,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from robotd.viz.frames import Pose2, covariance_6x6, covariance_ellipse, yaw_quaternion

MAP, ODOM, BASE_LINK, BEACON = "map", "odom", "base_link", "beacon"
FIX_LIFETIME_S = 30.0  # a fix stays in the scene this long: the last few seconds of the gate's decisions
FIX_DIAMETER_M = 0.06
BEACON_DIAMETER_M = 0.15
ELLIPSE_THICKNESS_M = 0.01
LABEL_HEIGHT_M = 0.3

VERDICT_COLOURS: dict[str, tuple[float, float, float, float]] = {
    "accepted": (0.1, 0.75, 0.2, 0.9),  # green: fused
    "seeded": (0.2, 0.4, 1.0, 0.9),  # blue: placed the position
    "recovered": (0.0, 0.8, 0.9, 0.9),  # cyan: re-seeded the position after a lock-out
    "seeding": (0.6, 0.6, 0.6, 0.9),  # grey: held until enough fixes agree
    "gated": (0.95, 0.15, 0.1, 0.9),  # red: rejected by the gate
    "unconfirmed": (0.95, 0.45, 0.6, 0.9),  # pink: inside a wide gate, far from the estimate; the next fix decides
    "too_old": (1.0, 0.6, 0.0, 0.9),  # orange: measured before the filter's history
    "dropped": (0.0, 0.0, 0.0, 0.9),  # black: not finite, never judged
}
"""The colour of a fix by the gate's verdict (robotd.estimation.modes.Verdict values)."""
FUSED_COLOUR = (0.2, 0.4, 1.0, 1.0)
BEACON_COLOUR = (0.55, 0.25, 0.75, 1.0)


def stamp(t_ns: int) -> Timestamp:
    """A Foxglove timestamp from nanoseconds."""
    return Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


def _rotation(theta: float) -> Quaternion:
    qx, qy, qz, qw = yaw_quaternion(theta)
    return Quaternion(x=qx, y=qy, z=qz, w=qw)


def pose_message(p: Pose2) -> Pose:
    """A planar pose as Foxglove's (z 0, a rotation about z)."""
    return Pose(position=Vector3(x=p[0], y=p[1], z=0.0), orientation=_rotation(p[2]))


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def pose_in_frame(t_ns: int, pose: Pose2, frame: str = MAP) -> PoseInFrame:
    """A planar pose in `frame`."""
    return PoseInFrame(timestamp=stamp(t_ns), frame_id=frame, pose=pose_message(pose))


def odometry(t_ns: int, pose: Pose2, twist: Sequence[float], cov: Sequence[float], t: float) -> Odometry:
    """The fused pose with its covariance (the 3x3 of x, y, theta as ROS's 6x6) and the body twist; metadata `t` is
    the daemon's monotonic time of the pose (the pose socket's `t`), to match the two streams."""
    return Odometry(
        metadata=[KeyValuePair(key="t", value=repr(t))],
        timestamp=stamp(t_ns),
        frame_id=MAP,
        body_frame_id=BASE_LINK,
        pose=pose_message(pose),
        linear_velocity=Vector3(x=twist[0], y=twist[1], z=0.0),
        angular_velocity=Vector3(x=0.0, y=0.0, z=twist[2]),
        pose_covariance=covariance_6x6(cov),
    )


def trail(t_ns: int, poses: list[Pose], frame: str = MAP) -> PosesInFrame:
    """A trail of poses (each built by `pose_message`), oldest first."""
    return PosesInFrame(timestamp=stamp(t_ns), frame_id=frame, poses=poses)


def ellipse(t_ns: int, center: tuple[float, float], cov: Sequence[float]) -> SceneUpdate:
    """The 95 % region of the fused position, as a closed line in the map."""
    points = [Point3(x=x, y=y, z=0.0) for x, y in covariance_ellipse(center, cov)]
    line = LinePrimitive(
        type=LinePrimitiveLineType.LineStrip,
        thickness=ELLIPSE_THICKNESS_M,
        points=points,
        color=_colour(FUSED_COLOUR),
    )
    entity = SceneEntity(timestamp=stamp(t_ns), frame_id=MAP, id="covariance-95", lines=[line])
    return SceneUpdate(entities=[entity])


def fix_marker(t_ns: int, number: int, at_xy: tuple[float, float], verdict: str, nis: float | None) -> SceneUpdate:
    """One IPS fix as a dot coloured by its verdict, labelled with it (and its NIS), kept for FIX_LIFETIME_S."""
    colour = _colour(VERDICT_COLOURS.get(verdict, VERDICT_COLOURS["dropped"]))
    at = pose_message((at_xy[0], at_xy[1], 0.0))
    label = verdict if nis is None else f"{verdict} (NIS {nis:.1f})"
    entity = SceneEntity(
        timestamp=stamp(t_ns),
        frame_id=MAP,
        id=f"fix-{number}",
        lifetime=Duration.from_secs(FIX_LIFETIME_S),
        spheres=[
            SpherePrimitive(pose=at, size=Vector3(x=FIX_DIAMETER_M, y=FIX_DIAMETER_M, z=FIX_DIAMETER_M), color=colour)
        ],
        texts=[TextPrimitive(pose=at, billboard=True, font_size=12.0, scale_invariant=True, color=colour, text=label)]
        if verdict not in ("accepted", "seeding")
        else [],  # only the fixes worth a look are labelled: a label per accepted fix would hide the scene
    )
    return SceneUpdate(entities=[entity])


def label(
    t_ns: int, entity_id: str, text: str, frame: str, rgba: tuple[float, float, float, float] = FUSED_COLOUR
) -> SceneUpdate:
    """A text facing the viewer LABEL_HEIGHT_M above the origin of `frame` (it moves with the frame)."""
    at = Pose(position=Vector3(x=0.0, y=0.0, z=LABEL_HEIGHT_M), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    text_primitive = TextPrimitive(
        pose=at, billboard=True, font_size=14.0, scale_invariant=True, color=_colour(rgba), text=text
    )
    return SceneUpdate(
        entities=[SceneEntity(timestamp=stamp(t_ns), frame_id=frame, id=entity_id, texts=[text_primitive])]
    )


def beacons(t_ns: int, stationary: Iterable[tuple[int, float, float, float, bool]]) -> SceneUpdate:
    """The stationary beacons of the Marvelmind map (address, x, y, z, applicable), labelled with their address."""
    entities = []
    for address, x, y, z, applicable in stationary:
        rgba = BEACON_COLOUR if applicable else (0.5, 0.5, 0.5, 0.5)
        at = Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        size = Vector3(x=BEACON_DIAMETER_M, y=BEACON_DIAMETER_M, z=BEACON_DIAMETER_M)
        entities.append(
            SceneEntity(
                timestamp=stamp(t_ns),
                frame_id=MAP,
                id=f"beacon-{address}",
                spheres=[SpherePrimitive(pose=at, size=size, color=_colour(rgba))],
                texts=[
                    TextPrimitive(
                        pose=at,
                        billboard=True,
                        font_size=14.0,
                        scale_invariant=True,
                        color=_colour(rgba),
                        text=f"beacon {address}",
                    )
                ],
            )
        )
    return SceneUpdate(entities=entities)


def transforms(t_ns: int, correction: Pose2, odom: Pose2, lever_arm: tuple[float, float]) -> FrameTransforms:
    """map -> odom (the filter's correction), odom -> base_link (dead reckoning), base_link -> beacon (lever arm)."""
    edges = ((MAP, ODOM, correction), (ODOM, BASE_LINK, odom), (BASE_LINK, BEACON, (lever_arm[0], lever_arm[1], 0.0)))
    return FrameTransforms(transforms=[frame_transform(t_ns, parent, child, p) for parent, child, p in edges])


def frame_transform(t_ns: int, parent: str, child: str, pose: Pose2) -> FrameTransform:
    """The transform that places frame `child` at `pose` in frame `parent`."""
    return FrameTransform(
        timestamp=stamp(t_ns),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=pose[0], y=pose[1], z=0.0),
        rotation=_rotation(pose[2]),
    )
