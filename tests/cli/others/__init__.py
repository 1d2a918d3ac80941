"""Whole runs on devices whose code hilcal's developers did not write or wrote apart from the drivers."""
