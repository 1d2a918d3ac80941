"""Tests of the laser tracker driver (Leica emScon) against the simulated tracker and cesapi."""
