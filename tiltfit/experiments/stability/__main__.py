"""`python -m tiltfit.experiments.stability` is `tiltfit stability`."""
import sys

from tiltfit.experiments.stability import main

sys.exit(main())
