"""Calibration: boards, corner detection, intrinsics and stereo pose, the rig and its world frame."""
