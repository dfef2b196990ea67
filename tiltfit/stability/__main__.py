"""`python -m tiltfit.stability` is `tiltfit stability`."""
import sys

from . import main

sys.exit(main())
