"""Subcommands of the `phasecal` CLI, one module each (see `api.cli`)."""
