"""Registration of scans, after Open3D's ``pipelines.registration`` layout (docs/registration.md).

``icp`` point-to-plane ICP, its coarse-to-fine schedule and its scoring (NumPy/SciPy); ``normals`` PCA normals of
the k nearest neighbours; ``global_registration`` FPFH + RANSAC (Open3D, imported at its first call); ``overlap``
the overlap of two scans and the pairs of a job; ``sampling`` voxel and even thinning; ``pairs`` one pair by the
configured method, verified; ``pose_graph`` the global refinement over all scans and tracker stations; ``mount_unknown``
the shared scanner-mount unknown in it; ``correction`` the whole-job correction (pairs -> joint refinement, or
pairs -> edges -> pose graph where it is off); ``joint`` the joint multi-view refinement of every pose on the
overlap points; ``online_pairs`` the pairs and the joint association found while the job measures; ``parallel`` one
thread per core for per-pair (and per-group) work. The learned global registration (DeepMerge) lives beside this
package in ``pipeline.deepmerge``.
"""
