"""Allow ``python -m microctl``."""

from microctl.cli import main

raise SystemExit(main())
