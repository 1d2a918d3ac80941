"""Devices written by others from the standards, behind an information barrier: test peers hilcal did not shape."""
