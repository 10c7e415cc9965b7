"""Hand-eye calibration: where the camera sits on a robot (or beside it) and where the target
is, from robot poses and the camera's own target poses (phasecal.handeye/1).

`rigid` the transforms, `robot_poses` the phasecal.robot-poses/1 input, `view_poses` each
view's target pose and covariance from a fitted camera, `classical` the classical start
values, `joint` the weighted refinement with covariance, `heldout` the leave-one-out check,
`solve` the whole estimate and its phasecal.handeye/1 form, `pipeline` files in, file out.
"""
