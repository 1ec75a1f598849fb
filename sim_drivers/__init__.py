"""The simulated cell: the world (ground truth), device twins and protocol emulators."""
