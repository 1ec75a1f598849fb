"""Training data and training of the shipped DeepMerge weights (CPU, fixed seed).

Data, made in code: a shape (``shapes``: generated families, and for ``part_fraction`` of the pairs the
simulated part) is sampled twice independently (two scans never share points); each scan keeps the points
facing its view direction within a crop radius around its centre, the second centre 0.3-0.9 crop radii from
the first (partial overlap), with noise along the normal. The overlap is extracted as at inference (except
for ``full_crop_fraction`` of the pairs, which keep the whole crops, as a registration without a usable
initial stitch sees them), normalised by the target, voxel-downsampled and turned into point structures.
Pose errors are drawn per batch and applied to the source (points and the rotating parts of its structure),
so one pool of pairs serves many errors: tracker-like (a few degrees, a few percent of the size) and, for
a fraction, arbitrary (up to ``arbitrary_deg``); the arbitrary share and size ramp up over the first
``curriculum`` of the steps. The loss of a pair is its error after each head iteration relative to its
error before (so fine and coarse pairs count alike), weighted towards the last iteration. Validation uses
shapes from a separate seed stream. Checkpoints (weights, settings, figures so far) are written as training
goes, so a run cut off by its time budget still leaves usable weights.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.deepmerge.features import reference_direction
from tandemscan.pipeline.deepmerge.model import WIDTHS, DeepMerge, rigid_errors
from tandemscan.pipeline.deepmerge.register import (
    COARSE_ITERATIONS,
    COARSE_POINTS,
    FINE_ITERATIONS,
    Normalisation,
    RegistrationError,
    prepare_cloud,
)
from tandemscan.pipeline.deepmerge.shapes import random_shape, simulated_part_mesh
from tandemscan.pipeline.registration.overlap import extract_overlap

log = logging.getLogger(__name__)

VAL_SEED_OFFSET = 1_000_003
#: structure channels that rotate with the cloud: offsets, normals, decentralised point, farthest point
_ROTATING = ((0, 3), (3, 6), (7, 10), (10, 13))


@dataclass(frozen=True)
class TrainSettings:
    """Everything that defines a training run (stored in the weights file)."""

    seed: int = 0
    # data: pairs in the pools, distinct generated shapes per pool
    train_pairs: int = 800
    val_pairs: int = 60
    shapes_per_pool: int = 40
    # network input: points per cloud (training, inference), neighbours k, voxel edge and iterations
    num_points: int = 256
    val_points: int = 1024       # validation pairs are cut at this many points, nearer the inference density
    num_points_inference: int = 2048
    k: int = 10
    voxel: float = 0.04          # of the target's RMS radius
    iterations: int = 4
    # inference (see ``register``): head iterations on a subset of points, then at all points (the last
    # trained iteration's parameters repeated)
    coarse_iterations: int = COARSE_ITERATIONS
    coarse_points: int = COARSE_POINTS
    iterations_inference: int = FINE_ITERATIONS
    widths: tuple[int, ...] = WIDTHS
    # optimisation: batch, Adam steps (cosine decay), learning rate, wall-clock budget including the data
    batch_size: int = 8
    steps: int = 6000
    lr: float = 1e-3
    max_minutes: float = 110.0
    checkpoint_every: int = 100    # steps between checkpoints (and validations) when writing weights
    # pose errors: tracker-like rotation (deg, 2 sigma) and translation (RMS radii, 2 sigma); a share of
    # arbitrary errors up to arbitrary_deg
    tracker_deg: float = 2.0
    tracker_trans: float = 0.04
    arbitrary_fraction: float = 0.25
    arbitrary_deg: float = 45.0
    curriculum: float = 0.3        # share of the steps over which the arbitrary errors ramp up
    loss_floor: float = 0.005      # added to a pair's initial error in the relative loss (rad + radii)
    noise_fraction: float = 0.003  # largest scanner noise, of the crop radius
    overlap_delta: float = 0.08    # overlap threshold of the aligned pair, of the crop radius
    use_part: bool = True          # add the simulated part to the shapes
    part_fraction: float = 0.2     # share of the pairs cut from the simulated part
    full_crop_fraction: float = 0.3  # share of the pairs that keep the whole crops (no overlap extraction)
    iteration_weights: tuple[float, ...] = field(default=(0.25, 0.5, 0.75, 1.0))


@dataclass
class PairPool:
    """Aligned training pairs as stacked arrays (normalised units)."""

    src_struct: np.ndarray
    tgt_struct: np.ndarray
    src_xyz: np.ndarray
    tgt_xyz: np.ndarray
    ref: np.ndarray

    def __len__(self) -> int:
        return len(self.src_xyz)


def _scan(points: np.ndarray, normals: np.ndarray, centre_idx: int, radius: float, rng: np.random.Generator,
          noise: float) -> np.ndarray:
    view = normals[centre_idx] + rng.normal(scale=0.4, size=3)
    view /= np.linalg.norm(view)
    keep = (np.linalg.norm(points - points[centre_idx], axis=1) < radius) & (normals @ view > 0.15)
    return points[keep] + rng.normal(scale=noise, size=(int(keep.sum()), 1)) * normals[keep]


class MeshSampler:
    """Two independent surface samplings (points, normals) of a mesh per pair, and its diagonal (mm).

    ``dense`` > 0: the mesh is sampled once with that many points and each pair splits the sample into two
    disjoint random halves (for a large part, whose scans cover a small share of it).
    """

    def __init__(self, mesh, dense: int = 0) -> None:
        self.mesh = mesh
        self.extent = float(np.linalg.norm(mesh.get_axis_aligned_bounding_box().get_extent()))
        self.dense = None
        if dense:
            pc = mesh.sample_points_uniformly(number_of_points=dense, use_triangle_normal=True)
            self.dense = (np.asarray(pc.points), np.asarray(pc.normals))

    def two(self, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
        if self.dense is not None:
            P, N = self.dense
            half = rng.random(len(P)) < 0.5
            return [(P[half], N[half]), (P[~half], N[~half])]
        out = []
        for _ in range(2):
            pc = self.mesh.sample_points_uniformly(number_of_points=int(rng.integers(30000, 60000)),
                                                   use_triangle_normal=True)
            out.append((np.asarray(pc.points), np.asarray(pc.normals)))
        return out


def make_pair(sampler: MeshSampler, rng: np.random.Generator, s: TrainSettings,
              crop: tuple[float, float] = (0.15, 0.3)) -> tuple[np.ndarray, ...] | None:
    """One aligned pair ``(src_struct, tgt_struct, src_xyz, tgt_xyz, ref)``, or None if too thin.

    The crop radius is drawn from ``crop`` (fractions of the mesh's bounding-box diagonal).
    """
    radius = rng.uniform(*crop) * sampler.extent
    (P1, N1), (P2, N2) = sampler.two(rng)
    c1 = int(rng.integers(len(P1)))
    d = np.linalg.norm(P2 - P1[c1], axis=1)
    cand = np.flatnonzero((d > 0.3 * radius) & (d < 0.9 * radius) & (N2 @ N1[c1] > 0.3))
    if len(cand) == 0:
        return None
    c2 = int(rng.choice(cand))
    noise = rng.uniform(0.0, s.noise_fraction) * radius
    A = _scan(P1, N1, c1, radius, rng, noise)
    B = _scan(P2, N2, c2, radius, rng, noise)
    if min(len(A), len(B)) < 500:
        return None
    if rng.random() >= s.full_crop_fraction:
        ov = extract_overlap(A, B, s.overlap_delta * radius)
        if ov.size < 300:
            return None
        A, B = A[ov.source_idx], B[ov.target_idx]
    norm = Normalisation.of(B)
    An, Bn = norm.apply(A), norm.apply(B)
    ref = reference_direction(Bn)
    try:
        sa, xa = prepare_cloud(An, s.num_points, s.k, s.voxel, ref, rng)
        sb, xb = prepare_cloud(Bn, s.num_points, s.k, s.voxel, ref, rng)
    except RegistrationError:
        return None
    if len(xa) < s.num_points or len(xb) < s.num_points:
        return None
    return sa, sb, xa, xb, ref.astype(np.float32)


#: crop radii of the simulated part's pairs (of its diagonal): a 3-4 m part, scans a few hundred mm across;
#: the part is sampled once this densely (about 4 mm spacing on the default part)
PART_CROP = (0.04, 0.1)
PART_SAMPLES = 1_500_000


def make_pool(n_pairs: int, seed: int, s: TrainSettings) -> PairPool:
    """``n_pairs`` pairs from ``s.shapes_per_pool`` shapes drawn from ``seed``, ``s.part_fraction`` of them
    from the simulated part (when ``s.use_part`` and the part generator is available)."""
    rng = np.random.default_rng(seed)
    o3d.utility.random.seed(seed % 2**31)           # Open3D's surface sampling has its own generator
    meshes = [MeshSampler(random_shape(rng)) for _ in range(s.shapes_per_pool)]
    part_mesh = simulated_part_mesh() if s.use_part else None
    part = MeshSampler(part_mesh, PART_SAMPLES) if part_mesh is not None else None
    items = []
    while len(items) < n_pairs:
        if part is not None and rng.random() < s.part_fraction:
            pair = make_pair(part, rng, s, PART_CROP)
        else:
            pair = make_pair(meshes[int(rng.integers(len(meshes)))], rng, s)
        if pair is not None:
            items.append(pair)
    cols = list(zip(*items, strict=True))
    return PairPool(*(np.stack(c) for c in cols))


def random_errors(rng: np.random.Generator, n: int, s: TrainSettings,
                  ramp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``(n, 3, 3)`` and translations ``(n, 3)`` (normalised units) of simulated pose errors.

    ``ramp`` (0-1) scales the share of arbitrary errors and their largest angle (from a quarter of it).
    """
    arbitrary = rng.random(n) < s.arbitrary_fraction * ramp
    top = s.arbitrary_deg * (0.25 + 0.75 * ramp)
    angle = np.where(arbitrary, rng.uniform(0, top, n), np.abs(rng.normal(0, s.tracker_deg / 2, n)))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R = Rotation.from_rotvec(axis * np.radians(angle)[:, None]).as_matrix()
    t = rng.normal(0, s.tracker_trans / 2, (n, 3)) * np.where(arbitrary, 5.0, 1.0)[:, None]
    return R, t


def perturb(src_struct: torch.Tensor, src_xyz: torch.Tensor, ref: torch.Tensor, R: torch.Tensor,
            t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Move the source by ``(R, t)`` about its centroid; returns the moved structure, points and the truth.

    The truth ``(R_true, t_true)`` maps the moved source back onto the target. Normals are re-oriented to
    ``ref`` as the inference preprocessing would.
    """
    m = src_xyz.mean(dim=1, keepdim=True)
    xyz = (src_xyz - m) @ R.transpose(1, 2) + m + t[:, None]
    st = src_struct.clone()
    for a, b in _ROTATING:
        st[..., a:b] = torch.einsum("bij,bnkj->bnki", R, src_struct[..., a:b])
    flip = torch.sign((st[..., 3:6] * ref[:, None, None, :]).sum(-1, keepdim=True))
    st[..., 3:6] = st[..., 3:6] * torch.where(flip == 0, torch.ones_like(flip), flip)
    R_true = R.transpose(1, 2)
    t_true = (m[:, 0] - (R_true @ (m[:, 0] + t)[..., None])[..., 0])
    return st, xyz, R_true, t_true


def _batch(pool: PairPool, idx: np.ndarray, rng: np.random.Generator, s: TrainSettings, ramp: float = 1.0):
    R, t = random_errors(rng, len(idx), s, ramp)
    f = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    st, xyz, R_true, t_true = perturb(f(pool.src_struct[idx]), f(pool.src_xyz[idx]), f(pool.ref[idx]),
                                      f(R.astype(np.float32)), f(t.astype(np.float32)))
    return st, f(pool.tgt_struct[idx]), xyz, f(pool.tgt_xyz[idx]), R_true, t_true


def evaluate(model: DeepMerge, pool: PairPool, s: TrainSettings, seed: int,
             inference: bool = False) -> dict[str, float]:
    """Median rotation (deg) and translation (percent of the RMS radius) errors, before and after.

    ``inference``: run the inference schedule of ``s`` (coarse iterations on a subset, then
    ``s.iterations_inference``) instead of the trained iterations. The errors drawn depend only on ``seed``.
    """
    rng = np.random.default_rng(seed)
    model.eval()
    res: dict[str, list[float]] = {k: [] for k in ("rot_in", "rot_out", "tr_in", "tr_out")}
    with torch.no_grad():
        for start in range(0, len(pool), s.batch_size):
            idx = np.arange(start, min(start + s.batch_size, len(pool)))
            st, tt, xs, xt, R_true, t_true = _batch(pool, idx, rng, s)
            if inference:
                R, t = model.infer(st, tt, xs, xt, s.iterations_inference, s.coarse_iterations, s.coarse_points)
            else:
                R, t = model(st, tt, xs, xt)[-1]
            for i in range(len(idx)):
                rot_in = Rotation.from_matrix(R_true[i].double().numpy()).magnitude()
                res["rot_in"].append(math.degrees(rot_in))
                D = R[i].double().numpy().T @ R_true[i].double().numpy()
                res["rot_out"].append(math.degrees(Rotation.from_matrix(D).magnitude()))
                # translation error at the target's centroid (the origin of the normalised frame)
                res["tr_in"].append(100 * float(t_true[i].norm()))
                res["tr_out"].append(100 * float((t[i] - t_true[i]).norm()))
    model.train()
    rin, rout = np.array(res["rot_in"]), np.array(res["rot_out"])
    tin, tout = np.array(res["tr_in"]), np.array(res["tr_out"])
    tracker = rin < s.tracker_deg * 2
    out = {"pairs": len(rin), "tracker_pairs": int(tracker.sum())}
    for name, mask in (("tracker", tracker), ("arbitrary", ~tracker)):
        if mask.any():
            out[f"{name}.rot_err_deg_median_before"] = float(np.median(rin[mask]))
            out[f"{name}.rot_err_deg_median_after"] = float(np.median(rout[mask]))
            out[f"{name}.trans_err_pct_median_before"] = float(np.median(tin[mask]))
            out[f"{name}.trans_err_pct_median_after"] = float(np.median(tout[mask]))
            out[f"{name}.success_rate"] = float(np.mean((rout[mask] < 1.0) & (tout[mask] < 1.0)))
    return out


def validate(model: DeepMerge, pool: PairPool, s: TrainSettings) -> dict[str, dict[str, float]]:
    """Validation figures with the trained iterations and with the inference schedule (same errors)."""
    return {"trained_iterations": evaluate(model, pool, s, s.seed + 1),
            "inference": evaluate(model, pool, s, s.seed + 1, inference=True)}


def pair_loss(model: DeepMerge, batch, s: TrainSettings) -> torch.Tensor:
    """Training loss of one batch: per pair, the error after each iteration over the error before (plus
    ``s.loss_floor``), weighted by ``s.iteration_weights`` (normalised) and averaged over the batch."""
    st, tt, xs, xt, R_true, t_true = batch
    eye = torch.eye(3, dtype=xs.dtype).expand_as(R_true)
    before = rigid_errors(eye, torch.zeros_like(t_true), R_true, t_true) + s.loss_floor
    w = list(s.iteration_weights[:s.iterations]) + [1.0] * max(0, s.iterations - len(s.iteration_weights))
    outs = model(st, tt, xs, xt)
    total = sum(wi * rigid_errors(R, t, R_true, t_true) for wi, (R, t) in zip(w, outs, strict=True))
    return (total / (sum(w) * before)).mean()


def train(s: TrainSettings, out_path: Path | None = None, progress=None) -> tuple[DeepMerge, dict]:
    """Train from scratch with ``s``; saves the weights, settings and validation to ``out_path`` if given.

    ``progress(step, loss)`` is called every 25 steps. Stops after ``s.steps`` or ``s.max_minutes``. With
    ``out_path``, a checkpoint with the validation figures so far is written every ``s.checkpoint_every``
    steps. Returns the model and a summary (losses, validation figures, time).
    """
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    t0 = time.monotonic()
    train_pool = make_pool(s.train_pairs, s.seed, s)
    val_pool = make_pool(s.val_pairs, s.seed + VAL_SEED_OFFSET, replace(s, num_points=s.val_points))
    data_s = time.monotonic() - t0
    log.info("made %d training and %d validation pairs in %.0f s", len(train_pool), len(val_pool), data_s)
    model = DeepMerge(iterations=s.iterations, widths=s.widths)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    budget_s = max(1.0, s.max_minutes * 60.0 - data_s)
    losses: list[float] = []
    step = 0

    def summary(final: bool) -> dict:
        val = validate(model, val_pool, s)
        out = {"steps": step, "final": final, "train_seconds": time.monotonic() - t0, "data_seconds": data_s,
               "loss_first_25": float(np.mean(losses[:25])), "loss_last_25": float(np.mean(losses[-25:])),
               "validation": val}
        log.info("step %d validation %s", step, val)
        return out

    t_train = time.monotonic()
    for step in range(1, s.steps + 1):
        # progress through the run by steps or by the time budget, whichever is further: the curriculum
        # and the cosine learning-rate decay then complete even when the budget ends the run early
        done = max((step - 1) / s.steps, (time.monotonic() - t_train) / budget_s)
        for g in opt.param_groups:
            g["lr"] = s.lr / 50 + (s.lr - s.lr / 50) * 0.5 * (1.0 + math.cos(math.pi * min(done, 1.0)))
        ramp = min(1.0, done / s.curriculum) if s.curriculum > 0 else 1.0
        idx = rng.choice(len(train_pool), size=s.batch_size, replace=False)
        loss = pair_loss(model, _batch(train_pool, idx, rng, s, ramp), s)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        losses.append(float(loss.detach()))
        if step % 25 == 0:
            log.info("step %d loss %.4f (%.0f s)", step, np.mean(losses[-25:]), time.monotonic() - t0)
            if progress is not None:
                progress(step, float(np.mean(losses[-25:])))
        if time.monotonic() - t_train > budget_s:
            log.info("stopping at step %d: time budget of %.0f min reached", step, s.max_minutes)
            break
        if out_path is not None and step % s.checkpoint_every == 0 and step < s.steps:
            save_weights(model, s, summary(False), out_path)
    result = summary(True)
    if out_path is not None:
        save_weights(model, s, result, out_path)
    return model, result


def save_weights(model: DeepMerge, s: TrainSettings, summary: dict, path: Path) -> None:
    """Write the weights with the settings the registrar needs and the training summary."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"state_dict": model.state_dict(), "settings": asdict(s), "summary": summary}, tmp)
    tmp.replace(path)
    log.info("wrote %s", path)
