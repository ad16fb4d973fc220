"""``python -m aumesh``: the same as the ``aumesh`` command (what the DVC stages run)."""

import sys

from aumesh.cli import main

sys.exit(main())
