"""Tests of hilcal/planning."""
