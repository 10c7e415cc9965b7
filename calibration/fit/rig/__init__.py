"""Joint calibration of several cameras (a rig): every camera's model, each camera's pose in
the reference camera's frame with its covariance, and the target pose of every view, in one
weighted least-squares fit over decoded maps and target observations.

Layout (imports point down): `calibrate` (the entry point) -> `start` (single-camera fits,
poses chained through the view graph), `problem` (the joint least squares), `heldout` ->
`blocks` (one camera's data in one view, whitened), `graph`, `inputs`, `options`,
`transforms`.
"""
