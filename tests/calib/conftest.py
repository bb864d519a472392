import pytest


@pytest.fixture(scope="session")
def session_dir(tmp_path_factory):
    """A small synthetic session (4 LEDs, diffuse, back light) with a 3 deg analyser offset."""
    from dualscale.sim.targets import Defects, SynthConfig, write_session

    root = tmp_path_factory.mktemp("calib") / "captures"
    truth = write_session(root, SynthConfig(led_step=32), Defects(analyzer_offset_deg=3.0),
                          parts=("white_sheet", "chart", "polarization"))
    return root, truth


@pytest.fixture(scope="session")
def calibration(session_dir):
    from dualscale.formats.captures import read_captures
    from dualscale.calib.pipeline import calibrate

    return calibrate(read_captures(session_dir[0]))
