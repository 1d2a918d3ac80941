"""Tests of hilcal/acquisition."""
