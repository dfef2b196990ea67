"""`python -m renderer ...` is the `renderer` command."""
import sys

from .cli import main

sys.exit(main())
