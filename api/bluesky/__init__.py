"""phasecal as part of a Bluesky-run lab: ophyd-async devices that drive a running phasecal
service over its REST API (`api.bluesky.devices`) and a plan that runs a whole calibration
session with them (`api.bluesky.plans`); docs/bluesky.md.

They need the optional extra `bluesky`: importing this package without it raises
`MissingExtra` with the install command, before any module here imports bluesky."""

from calibration.extras import require

require("bluesky", "phasecal's Bluesky devices and plans")
