"""robotd: a localisation daemon for a four-mecanum-wheel robot (wheel odometry + Marvelmind IPS, fused by an EKF)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("robotd")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"
