"""Tests of hilcal/acceptance."""
