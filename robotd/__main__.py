"""`python -m robotd` runs the command line."""

from robotd.cli import main

raise SystemExit(main())
