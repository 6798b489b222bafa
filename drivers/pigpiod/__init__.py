"""drivers.pigpiod."""
