"""robotd.offline."""
