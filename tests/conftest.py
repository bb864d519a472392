"""Suite-wide settings."""
import pytest
from hypothesis import settings

# No example database in the working tree, and the same examples on every run: CI must not
# pass or fail by the luck of the draw. `--hypothesis-seed` / a local profile can explore more.
settings.register_profile("dualscale", database=None, derandomize=True, deadline=None)
settings.load_profile("dualscale")


@pytest.fixture
def figures_not_drawn(monkeypatch):
    """``Assets.figure`` builds each figure but neither draws nor saves it (in this process):
    for the tests of a run report's words or of what a pipeline does around it, not of its
    figures (drawing them is most of a report's time; tests/report draws and checks them)."""
    import matplotlib.pyplot as plt

    from dualscale.report import html as rhtml

    def figure(self, fig, stem):
        plt.close(fig)
        return self.rel(self.dir / f"{self._name(stem)}.png")

    monkeypatch.setattr(rhtml.Assets, "figure", figure)
