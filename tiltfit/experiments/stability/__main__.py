"""`python -m tiltfit.experiments.stability` is `tiltfit stability`."""
import sys

from . import main

sys.exit(main())
