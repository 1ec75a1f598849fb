"""Geometry: frames, arm kinematics, the scanner's ray model, the part mesh, pose uncertainty (mm, rad)."""
