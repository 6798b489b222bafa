"""robotd.tools."""
