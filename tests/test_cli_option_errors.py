"""Issue 24 §3 (a fresh user's trial): a refused option value is refused before any work,
exit 2, and the message names the option the user typed (not an internal field)."""

from __future__ import annotations

import pytest

from dualscale.cli import main


@pytest.mark.parametrize("extra, option", [
    (["--ior-prior", "-1"], "--ior-prior"),
    (["--shadow-ratio", "1.5"], "--shadow-ratio"),
    (["--checkpoint-every", "0"], "--checkpoint-every"),
    (["--tile-px", "0", "--workers", "1"], "--tile-px"),
    (["--preset", "paper", "--ior-prior", "0.05"], "--ior-prior"),
])
def test_fit_refuses_a_bad_value_naming_the_option(tmp_path, capsys, extra, option):
    out = tmp_path / "o"
    assert main(["fit", str(tmp_path / "no-dataset"), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert option in err and "ior_prior_sd" not in err and "shadow_ratio" not in err, err
    assert "dataset not found" not in err  # checked before the dataset is even looked at
    assert not out.exists()


def test_a_sim_camera_off_the_simulated_rig_names_rig_for_digitize():
    """`digitize --rig /dev/ttyNOPE --camera sim:micro`: the message names --rig (digitize's
    option), not only capture's --port, and refuses before the serial port is opened."""
    from dualscale.cli.capture import rig_and_cameras
    from dualscale.errors import InputError

    with pytest.raises(InputError) as e:
        with rig_and_cameras("/dev/ttyNOPE", ["sim:micro"], ("micro", "mid")):
            pass
    msg = str(e.value)
    assert "--rig sim" in msg and "--port sim" in msg and "/dev/ttyNOPE" in msg
