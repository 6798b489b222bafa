"""robotd.sim."""
