"""Classical global registration: FPFH features matched by RANSAC (Open3D) (docs/registration.md, "Global stage").

For two clouds in millimetres without a usable initial pose. Both are thinned on a voxel grid of edge
``voxel_mm``; each thinned point gets a normal (neighbours within 2 voxels) and a Fast Point Feature
Histogram (neighbours within 5 voxels); RANSAC draws three mutually matched feature correspondences at a
time, rejects draws whose edge lengths disagree by more than 10 % or whose points land farther than 1.5
voxels apart, and keeps the rigid fit with most inliers. RANSAC runs on ``FeatureMatching.threads`` threads
(default one): Open3D's threads draw from one seeded generator in the order they get to it, so on several
threads one seed gives different draws from run to run, and on one the same answer every time
(tests/pipeline/registration/test_registration_stages.py; on one thread it was no slower on the bunny pairs). The result
``T_target_source`` (4x4 mm) is good to about a voxel: the fine stage (``icp.icp_coarse_to_fine``) finishes
it. Open3D is imported at the first call, so importing this module (as ``pairs`` does) costs nothing on a
path that never runs the global stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class FeatureMatching:
    """Settings of :func:`fpfh_ransac`: the voxel edge as a share of the target's bounding-box diagonal
    (so one setting serves a 150 mm bunny and a 3 m part), RANSAC's draws and confidence, its seed,
    and the threads Open3D may use for RANSAC (1: the same answer every run)."""

    voxel_fraction: float = 0.02
    max_iterations: int = 100_000
    confidence: float = 0.999
    seed: int = 0
    threads: int = 1

    def voxel_mm(self, target_mm: np.ndarray) -> float:
        """The voxel edge (mm) for this target."""
        return self.voxel_fraction * float(np.linalg.norm(np.ptp(target_mm, axis=0)))


def _thinned_with_features(points_mm: np.ndarray, voxel_mm: float):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_mm)).voxel_down_sample(voxel_mm)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel_mm, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel_mm, max_nn=100))
    return pcd, fpfh


def fpfh_ransac(source_mm: ArrayLike, target_mm: ArrayLike, settings: FeatureMatching = FeatureMatching()
                ) -> np.ndarray:
    """``T_target_source`` (4x4 mm) of two (N, 3) clouds by FPFH feature matching and RANSAC; the identity
    when no draw is consistent (the caller's verification then rejects it)."""
    S, T = np.asarray(source_mm, float), np.asarray(target_mm, float)
    voxel = settings.voxel_mm(T)
    if not voxel > 0:
        return np.eye(4)
    import open3d as o3d

    (src, f_src), (tgt, f_tgt) = _thinned_with_features(S, voxel), _thinned_with_features(T, voxel)
    reg = o3d.pipelines.registration
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(settings.threads)
    try:  # Open3D's own warnings (too few mutual matches: it falls back to all) would print past the caller
        o3d.utility.random.seed(settings.seed)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            res = reg.registration_ransac_based_on_feature_matching(
                src, tgt, f_src, f_tgt, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                reg.RANSACConvergenceCriteria(settings.max_iterations, settings.confidence))
    finally:
        o3d.utility.set_max_threads(threads)
    return np.asarray(res.transformation, float).copy()
