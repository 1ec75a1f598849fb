"""Training data and training of the shipped DeepMerge weights (CPU, fixed seed).

Data, made in code: a shape (``shapes``) is sampled twice independently (two scans never share points);
each scan keeps the points facing its view direction within a crop radius around its centre, the second
centre 0.3-0.9 crop radii from the first (partial overlap), with noise along the normal. The overlap is
extracted as at inference, normalised by the target, voxel-downsampled and turned into point structures.
Pose errors are drawn per batch and applied to the source (points and the rotating parts of its structure),
so one pool of pairs serves many errors: tracker-like (a few degrees, a few percent of the size) and, for
a fraction, arbitrary (up to ``arbitrary_deg``). Validation uses shapes from a separate seed stream.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tandemscan.pipeline.deepmerge.features import reference_direction
from tandemscan.pipeline.deepmerge.model import WIDTHS, DeepMerge, rigid_loss
from tandemscan.pipeline.deepmerge.overlap import extract_overlap
from tandemscan.pipeline.deepmerge.register import Normalisation, RegistrationError, prepare_cloud
from tandemscan.pipeline.deepmerge.shapes import random_shape, simulated_part_mesh

log = logging.getLogger(__name__)

VAL_SEED_OFFSET = 1_000_003
#: structure channels that rotate with the cloud: offsets, normals, decentralised point, farthest point
_ROTATING = ((0, 3), (3, 6), (7, 10), (10, 13))


@dataclass(frozen=True)
class TrainSettings:
    """Everything that defines a training run (stored in the weights file)."""

    seed: int = 0
    # data: pairs in the pools, distinct generated shapes per pool
    train_pairs: int = 600
    val_pairs: int = 60
    shapes_per_pool: int = 40
    # network input: points per cloud (training, inference), neighbours k, voxel edge and iterations
    num_points: int = 384
    num_points_inference: int = 2048
    k: int = 10
    voxel: float = 0.04          # of the target's RMS radius
    iterations: int = 3
    widths: tuple[int, ...] = WIDTHS
    # optimisation: batch, Adam steps (cosine decay), learning rate, wall-clock budget including the data
    batch_size: int = 8
    steps: int = 3000
    lr: float = 1e-3
    max_minutes: float = 110.0
    # pose errors: tracker-like rotation (deg, 2 sigma) and translation (RMS radii, 2 sigma); a share of
    # arbitrary errors up to arbitrary_deg
    tracker_deg: float = 2.0
    tracker_trans: float = 0.04
    arbitrary_fraction: float = 0.2
    arbitrary_deg: float = 45.0
    noise_fraction: float = 0.003  # largest scanner noise, of the crop radius
    overlap_delta: float = 0.08    # overlap threshold of the aligned pair, of the crop radius
    use_part: bool = True          # add the simulated part to the shapes
    iteration_weights: tuple[float, ...] = field(default=(0.5, 0.75, 1.0))


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


def make_pair(mesh, rng: np.random.Generator, s: TrainSettings) -> tuple[np.ndarray, ...] | None:
    """One aligned pair ``(src_struct, tgt_struct, src_xyz, tgt_xyz, ref)`` from ``mesh``, or None if too thin."""
    extent = float(np.linalg.norm(mesh.get_axis_aligned_bounding_box().get_extent()))
    radius = rng.uniform(0.15, 0.3) * extent
    clouds = []
    for _ in range(2):
        pc = mesh.sample_points_uniformly(number_of_points=int(rng.integers(30000, 60000)), use_triangle_normal=True)
        clouds.append((np.asarray(pc.points), np.asarray(pc.normals)))
    (P1, N1), (P2, N2) = clouds
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


def make_pool(n_pairs: int, seed: int, s: TrainSettings) -> PairPool:
    """``n_pairs`` pairs from ``s.shapes_per_pool`` shapes drawn from ``seed`` (plus the part if available)."""
    rng = np.random.default_rng(seed)
    meshes = [random_shape(rng) for _ in range(s.shapes_per_pool)]
    part = simulated_part_mesh() if s.use_part else None
    if part is not None:
        meshes.append(part)
    items = []
    while len(items) < n_pairs:
        pair = make_pair(meshes[int(rng.integers(len(meshes)))], rng, s)
        if pair is not None:
            items.append(pair)
    cols = list(zip(*items, strict=True))
    return PairPool(*(np.stack(c) for c in cols))


def random_errors(rng: np.random.Generator, n: int, s: TrainSettings) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``(n, 3, 3)`` and translations ``(n, 3)`` (normalised units) of simulated pose errors."""
    arbitrary = rng.random(n) < s.arbitrary_fraction
    angle = np.where(arbitrary, rng.uniform(0, s.arbitrary_deg, n), np.abs(rng.normal(0, s.tracker_deg / 2, n)))
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


def _batch(pool: PairPool, idx: np.ndarray, rng: np.random.Generator, s: TrainSettings):
    R, t = random_errors(rng, len(idx), s)
    f = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    st, xyz, R_true, t_true = perturb(f(pool.src_struct[idx]), f(pool.src_xyz[idx]), f(pool.ref[idx]),
                                      f(R.astype(np.float32)), f(t.astype(np.float32)))
    return st, f(pool.tgt_struct[idx]), xyz, f(pool.tgt_xyz[idx]), R_true, t_true


def evaluate(model: DeepMerge, pool: PairPool, s: TrainSettings, seed: int) -> dict[str, float]:
    """Median rotation (deg) and translation (percent of the RMS radius) errors, before and after."""
    rng = np.random.default_rng(seed)
    model.eval()
    res: dict[str, list[float]] = {k: [] for k in ("rot_in", "rot_out", "tr_in", "tr_out", "arb")}
    with torch.no_grad():
        for start in range(0, len(pool), s.batch_size):
            idx = np.arange(start, min(start + s.batch_size, len(pool)))
            st, tt, xs, xt, R_true, t_true = _batch(pool, idx, rng, s)
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
    tracker = rin < s.tracker_deg * 2
    out = {"pairs": len(rin), "tracker_pairs": int(tracker.sum())}
    for name, mask in (("tracker", tracker), ("arbitrary", ~tracker)):
        if mask.any():
            out[f"{name}.rot_err_deg_median_before"] = float(np.median(rin[mask]))
            out[f"{name}.rot_err_deg_median_after"] = float(np.median(rout[mask]))
            out[f"{name}.trans_err_pct_median_before"] = float(np.median(np.array(res["tr_in"])[mask]))
            out[f"{name}.trans_err_pct_median_after"] = float(np.median(np.array(res["tr_out"])[mask]))
            out[f"{name}.success_rate"] = float(np.mean((rout[mask] < 1.0) & (np.array(res["tr_out"])[mask] < 1.0)))
    return out


def train(s: TrainSettings, out_path: Path | None = None, progress=None) -> tuple[DeepMerge, dict]:
    """Train from scratch with ``s``; saves the weights, settings and validation to ``out_path`` if given.

    ``progress(step, loss)`` is called every 25 steps. Stops after ``s.steps`` or ``s.max_minutes``.
    Returns the model and a summary (losses, validation figures, time).
    """
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    t0 = time.monotonic()
    train_pool = make_pool(s.train_pairs, s.seed, s)
    val_pool = make_pool(s.val_pairs, s.seed + VAL_SEED_OFFSET, s)
    data_s = time.monotonic() - t0
    log.info("made %d training and %d validation pairs in %.0f s", len(train_pool), len(val_pool), data_s)
    model = DeepMerge(iterations=s.iterations, widths=s.widths)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=s.steps, eta_min=s.lr / 50)
    weights = list(s.iteration_weights) + [1.0] * max(0, s.iterations - len(s.iteration_weights))
    losses: list[float] = []
    step = 0
    for step in range(1, s.steps + 1):
        idx = rng.choice(len(train_pool), size=s.batch_size, replace=False)
        st, tt, xs, xt, R_true, t_true = _batch(train_pool, idx, rng, s)
        outs = model(st, tt, xs, xt)
        loss = sum(w * rigid_loss(R, t, R_true, t_true) for w, (R, t) in zip(weights, outs, strict=False))
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if step % 25 == 0:
            log.info("step %d loss %.4f", step, np.mean(losses[-25:]))
            if progress is not None:
                progress(step, float(np.mean(losses[-25:])))
        if (time.monotonic() - t0) / 60.0 > s.max_minutes:
            log.info("stopping at step %d: time budget of %.0f min reached", step, s.max_minutes)
            break
    validation = evaluate(model, val_pool, s, seed=s.seed + 1)
    summary = {"steps": step, "train_seconds": time.monotonic() - t0, "data_seconds": data_s,
               "loss_first_25": float(np.mean(losses[:25])), "loss_last_25": float(np.mean(losses[-25:])),
               "validation": validation}
    if out_path is not None:
        save_weights(model, s, summary, out_path)
    return model, summary


def save_weights(model: DeepMerge, s: TrainSettings, summary: dict, path: Path) -> None:
    """Write the weights with the settings the registrar needs and the training summary."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": model.state_dict(), "settings": asdict(s), "summary": summary}, path)
    log.info("wrote %s", path)
