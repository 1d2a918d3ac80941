"""Tests of hilcal/discovery."""
