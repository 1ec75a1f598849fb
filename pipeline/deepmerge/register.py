"""Run DeepMerge on two clouds in millimetres: normalise, build point structures, infer, denormalise.

Both clouds are given in one frame (after the tracker stitch, or after ``init``); the result is the 4x4
``T_target_source`` (mm) that maps source points onto the target. The network sees coordinates centred on
the target's centroid and divided by its RMS radius, voxel-downsampled at ``voxel`` of that radius, so one
set of weights serves a 150 mm bunny and a 3 m train nose alike.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike
from tandemscan.pipeline.deepmerge.features import plane_normals, point_structure, reference_direction
from tandemscan.pipeline.deepmerge.model import DeepMerge
from tandemscan.pipeline.geometry.frames import make_transform
from tandemscan.pipeline.registration.sampling import voxel_downsample

log = logging.getLogger(__name__)

WEIGHTS_NAME = "deepmerge.pt"
#: inference defaults: head iterations on a subset of points first, then at all points (docs/deepmerge.md)
COARSE_ITERATIONS = 48
COARSE_POINTS = 512
FINE_ITERATIONS = 2


class RegistrationError(ValueError):
    """The clouds cannot be registered (too few points, bad shapes) or the weights cannot be loaded."""


def shipped_weights_path() -> Path:
    """The trained weights shipped inside the package."""
    return Path(str(resources.files("tandemscan.pipeline.deepmerge").joinpath("weights", WEIGHTS_NAME)))


@dataclass(frozen=True)
class Normalisation:
    """``p_normalised = (p_mm - centre_mm) / scale_mm``."""

    centre_mm: np.ndarray
    scale_mm: float

    @classmethod
    def of(cls, target_mm: np.ndarray) -> Normalisation:
        """Centre on the target's centroid, scale by its RMS radius."""
        c = target_mm.mean(axis=0)
        s = float(np.sqrt(((target_mm - c) ** 2).sum(axis=1).mean()))
        if not s > 0:
            raise RegistrationError("target cloud has zero extent")
        return cls(c, s)

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        return (points_mm - self.centre_mm) / self.scale_mm

    def to_mm(self, R: np.ndarray, t_normalised: np.ndarray) -> np.ndarray:
        """4x4 (mm) of a transform estimated between normalised clouds."""
        c = self.centre_mm
        return make_transform(R, self.scale_mm * t_normalised + c - R @ c)


def prepare_cloud(
    points: np.ndarray, num_points: int, k: int, voxel: float, orient_to: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``(structure (n, k, 14) float32, xyz (n, 3) float32)`` of a normalised cloud, n <= num_points."""
    V = voxel_downsample(points, voxel)
    if len(V) < max(k, 3):
        raise RegistrationError(f"only {len(V)} points after voxel downsampling, need at least {k}")
    centres = np.sort(rng.choice(len(V), size=min(num_points, len(V)), replace=False))
    normals = plane_normals(V, k, orient_to)
    return point_structure(V, k, centres, normals), V[centres].astype(np.float32)


class DeepMergeRegistrar:
    """A trained :class:`DeepMerge` with its preprocessing and inference settings.

    Inference embeds up to ``num_points`` points per cloud once, runs ``coarse_iterations`` head iterations
    on a random ``coarse_points`` subset of them (cheap: the head costs the product of the two point
    counts), then ``iterations`` at all points. The head converges linearly along the weakly constrained
    directions of a patch (a tangential slide against a rotation), so many cheap iterations pay.
    """

    def __init__(self, model: DeepMerge, num_points: int = 2048, k: int = 10, voxel: float = 0.04,
                 iterations: int | None = None, coarse_iterations: int = 0,
                 coarse_points: int = COARSE_POINTS, rounds: int = 1, round_tolerance_deg: float = 0.05,
                 round_tolerance: float = 5e-4) -> None:
        """The network and its settings (the class doc). Ten parameters: the model, then each setting with the
        default the shipped weights use, kept as the registrar's attributes."""
        self.model = model.eval()
        self.num_points = num_points
        self.k = k
        self.voxel = voxel
        self.iterations = iterations or model.iterations
        self.coarse_iterations = coarse_iterations
        self.coarse_points = coarse_points
        self.rounds = rounds
        self.round_tolerance_deg = round_tolerance_deg
        self.round_tolerance = round_tolerance

    @classmethod
    def load(cls, path: Path | str | None = None, num_points: int | None = None, rounds: int = 1
             ) -> DeepMergeRegistrar:
        """Weights from ``path`` (default: shipped); settings (k, voxel, head iterations at inference) come
        from the file; ``rounds`` re-embedding rounds (see :meth:`register`)."""
        path = Path(path) if path is not None else shipped_weights_path()
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except (OSError, RuntimeError) as e:
            raise RegistrationError(f"{path}: cannot load DeepMerge weights: {e}") from e
        s = ckpt["settings"]
        model = DeepMerge(iterations=int(s["iterations"]), widths=tuple(s["widths"]))
        try:
            model.load_state_dict(ckpt["state_dict"])
        except RuntimeError as e:
            raise RegistrationError(f"{path}: weights do not fit the network: {e}") from e
        return cls(model, num_points=num_points or int(s["num_points_inference"]), k=int(s["k"]),
                   voxel=float(s["voxel"]), iterations=int(s.get("iterations_inference", s["iterations"])),
                   coarse_iterations=int(s.get("coarse_iterations", 0)),
                   coarse_points=int(s.get("coarse_points", COARSE_POINTS)), rounds=rounds)

    def register(self, source_mm: ArrayLike, target_mm: ArrayLike, seed: int = 0) -> np.ndarray:
        """``T_target_source`` (4x4, mm) that aligns ``source_mm`` onto ``target_mm`` (both (N, 3), mm).

        Runs up to ``rounds`` rounds: each moves the source by the estimate so far and embeds it afresh (the
        point structure is not rotation invariant, so its embedding matches the target's better the closer
        the clouds are), and the rounds stop early once one changes the estimate by less than
        ``round_tolerance_deg`` and ``round_tolerance`` RMS radii of the target.
        """
        S = np.asarray(source_mm, dtype=float)
        T = np.asarray(target_mm, dtype=float)
        for name, P in (("source", S), ("target", T)):
            if P.ndim != 2 or P.shape[1] != 3 or len(P) < self.k:
                raise RegistrationError(f"{name}: need an (N, 3) array with N >= {self.k}, got {P.shape}")
        norm = Normalisation.of(T)
        M = np.eye(4)
        for r in range(self.rounds):
            step = self._register_once(S @ M[:3, :3].T + M[:3, 3], T, norm, seed + r)
            M = step @ M
            angle = np.degrees(np.arccos(np.clip((np.trace(step[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
            moved = np.linalg.norm(step[:3, :3] @ norm.centre_mm + step[:3, 3] - norm.centre_mm)
            if angle < self.round_tolerance_deg and moved < self.round_tolerance * norm.scale_mm:
                break
        return M

    def _register_once(self, S: np.ndarray, T: np.ndarray, norm: Normalisation, seed: int) -> np.ndarray:
        """One round of :meth:`register`: the network's ``T_target_source`` (4x4 mm) of S onto T (mm)."""
        Sn, Tn = norm.apply(S), norm.apply(T)
        rng = np.random.default_rng(seed)
        ref = reference_direction(Tn)
        s_struct, s_xyz = prepare_cloud(Sn, self.num_points, self.k, self.voxel, ref, rng)
        t_struct, t_xyz = prepare_cloud(Tn, self.num_points, self.k, self.voxel, ref, rng)
        with torch.no_grad():
            R, t = self.model.infer(*(torch.from_numpy(a)[None] for a in (s_struct, t_struct, s_xyz, t_xyz)),
                                    self.iterations, self.coarse_iterations, self.coarse_points, seed)
        # the network runs in float32: project onto the nearest rotation in float64 before it becomes a pose
        U, _, Vt = np.linalg.svd(R[0].double().numpy())
        return norm.to_mm(U @ Vt, t[0].double().numpy())
