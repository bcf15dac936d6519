"""``python -m train.evaluate``: see :mod:`train.evaluate`."""

import sys

from .command import main

sys.exit(main())
