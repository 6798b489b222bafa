"""robotd.daemon.service."""
