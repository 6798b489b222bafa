"""robotd.estimation."""
