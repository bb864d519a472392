"""``python -m dualscale.cli``: the same as the ``dualscale`` command."""

import sys

from . import main

sys.exit(main())
