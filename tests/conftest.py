"""Suite-wide settings."""
from hypothesis import settings

# No example database in the working tree, and the same examples on every run: CI must not
# pass or fail by the luck of the draw. `--hypothesis-seed` / a local profile can explore more.
settings.register_profile("dualscale", database=None, derandomize=True, deadline=None)
settings.load_profile("dualscale")
