"""``python -m dualscale.cli``: the same as the ``dualscale`` command."""

from . import run

run()
