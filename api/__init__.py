"""The REST service, persistence and the command-line interface."""
