"""``python -m iiwa_torch.cli ...``: the ``iiwa-torch`` command."""

import sys

from . import main

sys.exit(main())
