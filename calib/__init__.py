"""Calibration of depth cameras: intrinsics, camera-to-robot extrinsics, camera-to-camera
refinement and the axial noise model, each writing ``[[camera]]`` configuration keys.

Modules: ``intrinsics`` (checkerboard, OpenCV), ``extrinsics`` (ArUco/AprilTag markers at known
base-frame poses, low-pass filtered; point correspondences by Kabsch), ``multi`` (ICP between
overlapping clouds), ``noise`` (sigma_z = a + b Z^2 from a plane at several distances),
``render`` (synthetic images with known ground truth, for tests and demos), ``output`` (the TOML
writer) and ``cli`` (``pointfence calib ...``).
"""
