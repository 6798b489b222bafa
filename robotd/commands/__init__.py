"""Sub-commands of the robotd command line, one module per capability."""
