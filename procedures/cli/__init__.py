"""The `hilcal` command line, the composition root above every package: one module per audience (see app.py)."""
