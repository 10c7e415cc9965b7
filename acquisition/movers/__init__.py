"""Mover backends and their checks: fewer-axis stage kinematics, the HTTP/JSON robot client,
the conformance kit. The protocol itself is `acquisition.mover`."""
