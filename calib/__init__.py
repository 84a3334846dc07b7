"""Calibration of depth cameras: intrinsics, camera-to-robot extrinsics, camera-to-camera
refinement and the axial noise model, each writing ``[[camera]]`` configuration keys.

Modules: ``intrinsics`` (checkerboard, OpenCV), ``extrinsics`` (ArUco/AprilTag markers at known
base-frame poses, low-pass filtered; point correspondences by Kabsch), ``multi`` (ICP between
overlapping clouds), ``noise`` (sigma_z = a + b Z^2 from a plane at several distances),
``render`` (synthetic images with known ground truth, for tests and demos), ``output`` (the TOML
writer) and ``cli`` (``pointfence calib ...``). Hand-eye (a fixed camera from the robot's logged
poses): ``handeye`` (the command), ``handeye_log`` (the log format), ``handeye_tip`` (the tip ball
in depth), ``handeye_solve`` (Kabsch, Park-Martin / OpenCV hand-eye, verdict), ``handeye_sim``
(synthetic logs); ``master_reg`` (``[teleop]`` T_world_master and scale).
"""
