"""`python -m tiltfit.experiments.reproduce`: the same as `tiltfit reproduce`."""
import sys

from .pipeline import main

sys.exit(main())
