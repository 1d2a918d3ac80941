"""``python -m procedures.cli``: the `hilcal` command line."""

from procedures.cli.app import app

app(prog_name="hilcal")
