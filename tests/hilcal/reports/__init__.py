"""Tests of hilcal/reports."""
