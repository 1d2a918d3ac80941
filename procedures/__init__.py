"""Procedures: plans that orchestrate drivers and the hilcal core."""
