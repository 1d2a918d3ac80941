"""Tests of hilcal."""
