"""The cell's calibration: the calibration job (:mod:`.calibrate`), the current calibration and the mounts a
job stitches with (:mod:`.current`), and interim verification on the plate (:mod:`.verify`).
docs/calibration.md.
"""
