"""`python -m renderer ...` is the `renderer` command."""
import sys

try:
    from renderer.cli.main import main

    sys.exit(main())
except KeyboardInterrupt:  # a Ctrl-C while the modules load, or after the command's own handler
    print("renderer: interrupted", file=sys.stderr)
    sys.exit(130)
