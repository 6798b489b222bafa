"""robotd.logs."""
