"""Calibration: plate spheres and plate frame (Eq. 7-8), hand-eye ``A X = X B`` (Eq. 9-12), mounts."""
