"""Operator programs: installing robotd on the robot and checking a freshly wired robot."""
