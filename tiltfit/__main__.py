"""`python -m tiltfit ...`: the same as the `tiltfit` command."""
import sys

from .cli import main

sys.exit(main())
