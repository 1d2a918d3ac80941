"""Tests of sim_devices."""
