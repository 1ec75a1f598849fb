"""The DeepMerge network (PyTorch): point-feature extractor, soft correspondences, differentiable SVD.

- Extractor: five 1x1 convolutions of widths 64, 64, 128, 256, 512. The first four run on the ``k x 14``
  point structure of every point; after each, a max-pool over the k neighbours gives a per-point feature,
  and the concatenation of those four pooled features (64+64+128+256 = 512 channels) feeds the last
  convolution, which gives a 512-dimensional embedding per point.
- Matching: the cosine similarity of source and target embeddings (times a learned gain), minus a learned
  multiple of the squared distance between the currently aligned source point and each target point, gives
  a similarity matrix; a softmax over the target points makes soft correspondences (a weighted target point
  per source point), shot along the matched normal with a learned share of its tangential part kept (two
  independent samplings of one surface carry no tangential information, and keeping all of it lets the
  estimate drift). The distance term is measured in units of the current residual (the median squared
  distance of the aligned source points to their nearest target point), so it sharpens by itself as the
  estimate improves and behaves alike at coarse and fine errors and at any point density.
- Confidence: a small per-point network on the source embedding, the correspondence peak and the point's
  nearest-neighbour distance (in residual units) weights each correspondence.
- Head: weighted Kabsch/Umeyama by SVD with the reflection fix, composed with the running estimate; the
  head is iterated ``iterations`` times (the embeddings are computed once, the distance term follows the
  current estimate, the running estimate is not differentiated through, so each iteration learns to improve
  on the one before). At inference more iterations than trained may be run: the last iteration's parameters
  are repeated.

Coordinates are normalised (see ``register``); the output maps source coordinates into target coordinates.
"""

from __future__ import annotations

import torch
from torch import nn

WIDTHS = (64, 64, 128, 256, 512)


def _block(cin: int, cout: int, conv: type[nn.Module]) -> nn.Sequential:
    return nn.Sequential(conv(cin, cout, 1), nn.LeakyReLU(0.2))


class PointFeatureExtractor(nn.Module):
    """``(B, N, k, 14)`` point structures -> ``(B, N, 512)`` embeddings."""

    def __init__(self, in_dim: int = 14, widths: tuple[int, ...] = WIDTHS) -> None:
        super().__init__()
        if len(widths) != 5:
            raise ValueError(f"the extractor has five convolutions, got widths {widths}")
        chans = (in_dim, *widths[:4])
        self.local = nn.ModuleList(_block(chans[i], chans[i + 1], nn.Conv2d) for i in range(4))
        self.last = _block(sum(widths[:4]), widths[4], nn.Conv1d)

    def forward(self, structure: torch.Tensor) -> torch.Tensor:
        x = structure.permute(0, 3, 2, 1)               # (B, 14, k, N): pooling over k is then a max of
        pooled = []                                     # k contiguous slices, fast on a CPU
        for layer in self.local:
            x = layer(x)
            pooled.append(x.amax(dim=2))                # (B, C, N)
        return self.last(torch.cat(pooled, dim=1)).transpose(1, 2)


def weighted_procrustes(
    source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, eps: float = 1e-9
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid ``(R, t)`` minimising ``sum w_i |R s_i + t - t_i|^2`` by SVD, with the reflection fix.

    ``source``, ``target``: ``(B, N, 3)``; ``weights``: ``(B, N)`` non-negative. Returns ``R (B, 3, 3)``
    with det +1 and ``t (B, 3)``. Differentiable.
    """
    w = weights / weights.sum(dim=1, keepdim=True).clamp_min(eps)
    cs = (w[..., None] * source).sum(dim=1)
    ct = (w[..., None] * target).sum(dim=1)
    H = (source - cs[:, None]).transpose(1, 2) @ (w[..., None] * (target - ct[:, None]))
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(1, 2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(1, 2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=1))
    R = V @ D @ U.transpose(1, 2)
    t = ct - (R @ cs[..., None]).squeeze(-1)
    return R, t


class DeepMerge(nn.Module):
    """Registration network. ``forward`` returns the running ``(R, t)`` after each head iteration."""

    def __init__(self, iterations: int = 3, widths: tuple[int, ...] = WIDTHS) -> None:
        super().__init__()
        self.iterations = iterations
        self.extractor = PointFeatureExtractor(widths=widths)
        # per iteration: log of the feature-similarity gain and of the distance penalty (in residual units);
        # the gain starts small so that the untrained head is a soft nearest-neighbour registration
        self.log_gain = nn.Parameter(torch.zeros(iterations))
        self.log_dist = nn.Parameter(torch.log(torch.logspace(0.0, 0.3, iterations)))
        # per iteration: share (logit) of the tangential part of a soft correspondence that is kept
        self.tangential_logit = nn.Parameter(torch.full((iterations,), -2.0))
        self.confidence = nn.Sequential(nn.Conv1d(widths[4] + 2, 64, 1), nn.LeakyReLU(0.2), nn.Conv1d(64, 1, 1))

    def embed(self, structure: torch.Tensor) -> torch.Tensor:
        """L2-normalised per-point embeddings ``(B, N, 512)``."""
        return nn.functional.normalize(self.extractor(structure), dim=2)

    def forward(
        self,
        src_structure: torch.Tensor,
        tgt_structure: torch.Tensor,
        src_xyz: torch.Tensor,
        tgt_xyz: torch.Tensor,
        iterations: int | None = None,
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Embed both clouds and run ``iterations`` head iterations (default the trained number)."""
        fs, ft = self.embed(src_structure), self.embed(tgt_structure)
        return self.iterate(fs, ft, src_xyz, tgt_xyz, tgt_structure[:, :, 0, 3:6], iterations or self.iterations)

    def infer(
        self,
        src_structure: torch.Tensor,
        tgt_structure: torch.Tensor,
        src_xyz: torch.Tensor,
        tgt_xyz: torch.Tensor,
        iterations: int,
        coarse_iterations: int = 0,
        coarse_points: int = 512,
        seed: int = 0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Inference schedule: embed once, ``coarse_iterations`` head iterations on a random subset of
        ``coarse_points`` points of each cloud (the head costs the product of the point counts), then
        ``iterations`` at all points. Returns the final ``(R, t)``.

        Eight parameters: both clouds' point structures and points as the network's tensors, and the inference
        schedule."""
        fs, ft, nt = self.embed(src_structure), self.embed(tgt_structure), tgt_structure[:, :, 0, 3:6]
        start, first = None, 0
        if coarse_iterations:
            g = torch.Generator().manual_seed(seed)
            i = torch.randperm(src_xyz.shape[1], generator=g)[:coarse_points].sort().values
            j = torch.randperm(tgt_xyz.shape[1], generator=g)[:coarse_points].sort().values
            start = self.iterate(fs[:, i], ft[:, j], src_xyz[:, i], tgt_xyz[:, j], nt[:, j], coarse_iterations)[-1]
            first = coarse_iterations
        return self.iterate(fs, ft, src_xyz, tgt_xyz, nt, iterations, start, first)[-1]

    def iterate(
        self,
        fs: torch.Tensor,
        ft: torch.Tensor,
        src_xyz: torch.Tensor,
        tgt_xyz: torch.Tensor,
        tgt_normals: torch.Tensor,
        iterations: int,
        start: tuple[torch.Tensor, torch.Tensor] | None = None,
        first: int = 0,
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Head iterations on embedded clouds: ``(R, t)`` after each.

        ``tgt_normals``: each target point's own normal (a point's first neighbour in its structure is
        itself). ``start``: the running estimate to begin from (default identity); ``first``: the index of
        the first iteration, whose parameters it uses (iterations past the trained ones repeat the last).

        Eight parameters: both clouds' embeddings and points, the target's normals, and how many iterations run from
        where.
        """
        tgt_xyzn = torch.cat([tgt_xyz, tgt_normals], dim=2)  # matched points and normals in one product
        tgt_sq = tgt_xyz.square().sum(dim=2)[:, None, :]
        feat_sim = fs @ ft.transpose(1, 2)              # (B, N, M) cosine similarity
        B = src_xyz.shape[0]
        if start is None:
            R = torch.eye(3, dtype=src_xyz.dtype, device=src_xyz.device).expand(B, 3, 3)
            t = torch.zeros(B, 3, dtype=src_xyz.dtype, device=src_xyz.device)
        else:
            R, t = start
        out = []
        for it in range(first, first + iterations):
            j = min(it, self.iterations - 1)
            R, t = R.detach(), t.detach()
            cur = src_xyz @ R.transpose(1, 2) + t[:, None]
            d2 = torch.baddbmm(tgt_sq + cur.square().sum(dim=2, keepdim=True), cur, tgt_xyz.transpose(1, 2),
                               alpha=-2.0).clamp_min_(0.0)
            nn2 = d2.min(dim=2).values                  # (B, N) squared nearest-neighbour distance
            scale = nn2.median(dim=1).values.clamp_min(1e-8)[:, None, None]
            logits = self.log_gain[j].exp() * feat_sim - self.log_dist[j].exp() * (d2 / scale)
            P = torch.softmax(logits, dim=2)
            mx = P @ tgt_xyzn
            matched = mx[..., :3]
            # normal shooting: the offset to the soft match along the matched normal, plus a learned share of
            # its tangential part (two independent samplings of a surface give no tangential information)
            n = nn.functional.normalize(mx[..., 3:], dim=2)
            off = matched - cur
            along = (off * n).sum(dim=2, keepdim=True) * n
            matched = cur + along + torch.sigmoid(self.tangential_logit[j]) * (off - along)
            peak = P.max(dim=2).values
            near = (nn2 / scale[..., 0]).clamp_max(100.0).log1p()
            conf_in = torch.cat([fs, peak[..., None], near[..., None]], dim=2).transpose(1, 2)
            w = torch.sigmoid(self.confidence(conf_in))[:, 0]
            dR, dt = weighted_procrustes(cur, matched, w)
            R = dR @ R
            t = (dR @ t[..., None]).squeeze(-1) + dt
            out.append((R, t))
        return out


def rigid_errors(R: torch.Tensor, t: torch.Tensor, R_true: torch.Tensor, t_true: torch.Tensor) -> torch.Tensor:
    """Per pair ``|R^T R_true - I|_F / sqrt(2) + |t - t_true|`` (about angle in rad + distance), ``(B,)``.

    Not squared, so small errors keep a useful gradient and the fit keeps improving at the fine end.
    """
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    rot = ((R.transpose(1, 2) @ R_true - eye).square().sum(dim=(1, 2)) / 2.0 + 1e-12).sqrt()
    trans = ((t - t_true).square().sum(dim=1) + 1e-12).sqrt()
    return rot + trans
