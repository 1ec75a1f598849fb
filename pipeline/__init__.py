"""Pure computation: frames, stitching, calibration, planning, DeepMerge, refinement, inspection, cloud I/O."""
