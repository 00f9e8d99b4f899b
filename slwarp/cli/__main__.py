"""`python -m slwarp.cli`: the `slwarp` command."""
import sys

from . import main

sys.exit(main())
