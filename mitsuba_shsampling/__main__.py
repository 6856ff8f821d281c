"""``python -m mitsuba_shsampling compare|bench``: see :mod:`mitsuba_shsampling.cli`."""

import sys

from .cli import main

sys.exit(main())
