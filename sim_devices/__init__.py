"""Simulated devices: an independent physical model of the rig, its controller and its CMM."""
