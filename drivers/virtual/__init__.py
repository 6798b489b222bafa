"""drivers.virtual."""
