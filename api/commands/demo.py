"""`phasecal demo`: full simulated acquisition, decoding and calibration (see `api.demo`).

The interim demo of the acquisition work was superseded by the service-level demo in
`api.demo`, which drives the simulated rig through the controller over HTTP; this module
only registers it as a CLI subcommand.
"""

from api.demo import HELP, add_arguments, run

__all__ = ["HELP", "add_arguments", "run"]
