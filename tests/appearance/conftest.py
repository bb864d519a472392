import sys
from pathlib import Path

import pytest

_HOST = Path(__file__).resolve().parents[2] / "host"
if str(_HOST) not in sys.path:
    sys.path.insert(0, str(_HOST))


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: longer-running appearance tests")


from hypothesis import settings  # noqa: E402

# no example database in the working tree; deterministic runs for CI
settings.register_profile("appearance", database=None, derandomize=True, deadline=None)
settings.load_profile("appearance")
