"""Stitching: the voxel world map, AGV relocalisation and the mount installation of a job."""
