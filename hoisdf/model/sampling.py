"""Query-point sampling for the pose stage: ground-truth guided (training) and field guided (inference).

Coordinates: "scaled" points are metric offsets from a centre (hand root or object pseudo-centre) times
``sdf_scale`` (3.1), so the 64^3 grid spans [-1, 1]^3 = a cube of +-32 cm around the centre.

Field-guided sampling is batched over the batch: every sample's grid is projected with its own
intrinsics, the points strictly inside its 2D box are moved to the front (a stable sort of the
inside flags), and the SDF decoder runs on the first ``M = max(inside count, n)`` columns of every row in
chunks. Columns outside a sample's box are ranked after all of its inside points, so a box holding
fewer than ``n`` grid points still yields ``n`` points (the reference code crashes there).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from hoisdf.model.encoding import project_points

SdfFn = Callable[[torch.Tensor], torch.Tensor]  # camera points (B, M, 3) -> scaled SDF (B, M)
STRATEGIES = ("absolute", "signed", "random", "gradient")
_OUTSIDE = 1e4  # added to the score of points outside the box so they rank last


def noise_scale(progress: float, ratios: tuple[float, ...] = (0.3, 0.7),
                dists: tuple[float, ...] = (0.03, 0.05, 0.07)) -> float:
    """Noise half-width (scaled units) for the within-epoch progress in [0, 1]: dists[#ratios exceeded]."""
    return dists[sum(progress > r for r in ratios)]


def jitter(points: torch.Tensor, half_width: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """points (B, N, 3) + per-coordinate uniform noise in [-half_width, half_width] (drawn on the CPU)."""
    noise = (torch.rand(points.shape, generator=generator) * 2 - 1) * half_width
    return points + noise.to(points)


def grid_points(resolution: int, sheared: bool = False, device=None) -> torch.Tensor:
    """(resolution^3, 3) lattice over [-1, 1]^3 in scaled units, x slowest.

    ``sheared=True`` reproduces the reference code's lattice, whose index arithmetic used true division,
    so x and y pick up fractions of the faster indices (x, y reach ~1.03) - only for matching released numbers.
    """
    n = resolution
    idx = torch.arange(n ** 3, device=device, dtype=torch.float64)
    c = torch.remainder(idx, n)
    if sheared:
        b, a = idx / n, idx / n ** 2
    else:
        b, a = torch.remainder(torch.div(idx, n, rounding_mode="floor"), n), torch.div(idx, n * n, rounding_mode="floor")
    step = 2.0 / (n - 1)
    return (torch.stack([a, b, c], dim=1) * step - 1.0).float()


def inside_box(points_cam: torch.Tensor, K: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """(B, N) bool: the projection of each camera point lies strictly inside its sample's box (x1, y1, x2, y2).

    Points at or behind the camera (z <= 0) are never inside.
    """
    uv = project_points(points_cam, K)
    x, y = uv[..., 0], uv[..., 1]
    b = box[:, None, :]
    return (x > b[..., 0]) & (x < b[..., 2]) & (y > b[..., 1]) & (y < b[..., 3]) & (points_cam[..., 2] > 0)


def _score(sdf: torch.Tensor, strategy: str, generator: torch.Generator | None) -> torch.Tensor:
    if strategy in ("absolute", "gradient"):
        return sdf.abs()
    if strategy == "signed":
        return sdf
    return torch.rand(sdf.shape, generator=generator).to(sdf)  # random


def field_guided_points(grid: torch.Tensor, center: torch.Tensor, scale: float, K: torch.Tensor, box: torch.Tensor,
                        sdf_fn: SdfFn, n: int, strategy: str = "absolute", chunk: int = 32768,
                        generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``n`` grid points per sample that the strategy ranks first among those inside the box.

    grid: (G, 3) scaled lattice (see :func:`grid_points`); center: (B, 3) camera-frame centre, metres;
    K: (B, 3, 3); box: (B, 4) in the same pixels as K; sdf_fn: camera points (B, M, 3) -> scaled SDF
    (B, M) of the field being sampled. ``strategy``: "absolute" smallest |SDF| (HOISDF), "signed" smallest
    SDF (deepest inside), "random" uniformly among the inside points, "gradient" as "absolute" and then
    one Newton step onto the surface along the SDF gradient.
    Returns (points (B, n, 3) scaled, relative to ``center``; sdf (B, n) scaled, from ``sdf_fn``).
    Runs without gradient, except the "gradient" step (which needs it for the points, not the weights).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"sampling strategy must be one of {STRATEGIES}, got {strategy!r}")
    B, G = center.shape[0], grid.shape[0]
    grid = grid.to(center)
    with torch.no_grad():
        inside = torch.cat([inside_box(grid[None, s:s + chunk] / scale + center[:, None], K, box)
                            for s in range(0, G, chunk)], dim=1)  # (B, G)
        m = min(G, max(int(inside.sum(1).max()), n))
        order = torch.argsort((~inside).to(torch.uint8), dim=1, stable=True)[:, :m]  # inside points first
        cand = grid[order]  # (B, m, 3)
        valid = torch.gather(inside, 1, order)
        sdf = torch.cat([sdf_fn(cand[:, s:s + chunk] / scale + center[:, None]) for s in range(0, m, chunk)], dim=1)
        score = _score(sdf, strategy, generator) + _OUTSIDE * (~valid)
        pick = torch.topk(score, n, dim=1, largest=False).indices
        points = torch.gather(cand, 1, pick[..., None].expand(B, n, 3))
        sdf = torch.gather(sdf, 1, pick)
    if strategy == "gradient":
        points, sdf = _newton_step(points, center, scale, sdf_fn)
    return points, sdf


def _newton_step(points: torch.Tensor, center: torch.Tensor, scale: float, sdf_fn: SdfFn):
    """Move each scaled point by -sdf * unit gradient (one projection step onto the zero level set)."""
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        sdf = sdf_fn(p / scale + center[:, None])
        (grad,) = torch.autograd.grad(sdf.sum(), p)
    unit = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    moved = (p - sdf[..., None] * unit).detach()
    with torch.no_grad():
        return moved, sdf_fn(moved / scale + center[:, None])

