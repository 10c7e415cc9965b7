"""Joint calibration of several cameras (a rig): every camera's model, each camera's pose in
the reference camera's frame with its covariance, and the target pose of every view, in one
weighted least-squares fit over decoded maps and target observations.

Layout (imports point down): `files` (read the inputs) -> `calibrate` (the entry point) ->
`start` (single-camera fits, poses chained through the view graph), `heldout`, `problem`
(the joint least squares) -> `blocks` (one camera's data in one view, whitened), `graph`,
`inputs`, `options`, `result`, `transforms`.
"""
