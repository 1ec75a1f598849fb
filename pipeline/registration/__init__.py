"""Registration of scans, after Open3D's ``pipelines.registration`` layout (docs/registration.md).

``icp`` point-to-plane ICP and its scoring, ``overlap`` the overlap of two scans and the pairs of a job,
``sampling`` voxel and even thinning, ``pairs`` one pair by the configured method, ``pose_graph`` the global
refinement over all scans and tracker stations, ``mounts`` the shared scanner-mount unknown in it,
``correction`` the whole-job correction (pairs -> edges -> pose graph). The learned global registration
(DeepMerge) lives beside it in ``pipeline.deepmerge``.
"""
