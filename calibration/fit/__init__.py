"""Estimators and optimizers that produce camera models from decoded maps.

Layout (imports only point down this list): `dispatch` (the one entry point) ->
families `classic/` (OpenCV parametric models and closed-form estimators), `raygrid/`,
`sgcc/` (raygrid starts from sgcc's initial poses) -> shared helpers `observations`,
`correspondences`, `heldout`, `result`, `ransac`.
"""
