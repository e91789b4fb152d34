"""``python -m flightsim``: see :mod:`flightsim.cli`."""

import sys

from flightsim.cli import main

sys.exit(main())
