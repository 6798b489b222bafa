"""drivers.wheels."""
