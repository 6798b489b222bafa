"""robotd.config.model."""
