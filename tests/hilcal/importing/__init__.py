"""Tests of hilcal/importing."""
