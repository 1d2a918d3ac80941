"""The run from start to end: resume, physics, adaptive plan, summary and certificate, through `hilcal run`."""
