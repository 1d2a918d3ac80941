"""hilcal: kinematic calibration of 6-6 Gough/Stewart platforms (pure math and data, no device I/O)."""

__version__ = "0.1.0"
