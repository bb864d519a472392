"""dualscale: host software for the dual-scale optical material-digitization rig."""

__version__ = "0.1.0"
