"""Query-point sampling for the pose stage: ground-truth guided (training) and field guided (inference).

Coordinates: "scaled" points are metric offsets from a centre (hand root or object pseudo-centre) times
``sdf_scale`` (3.1), so the 64^3 grid spans [-1, 1]^3 = a cube of +-32 cm around the centre.

Field-guided sampling ranks the grid points whose projection lies strictly inside the sample's 2D box and
keeps the first ``n``; ties (e.g. SDFs clamped at the same value) go to the lower grid index, and a box
holding fewer than ``n`` grid points is filled with the lowest-index points outside it (the reference code
crashes there). Two ways to compute it, selecting the same points (tested):

* compact (default): the inside points are moved to the front (a stable sort of the inside flags) and the
  SDF decoder runs on the first ``M = max(inside count, n)`` columns only; ``M`` depends on the data.
* fixed shape (``fixed_shape=True``): the decoder runs on the whole grid and the box is a mask on the scores;
  every shape is static, so the model compiles with ``torch.compile(fullgraph=True)`` and can be captured in
  a CUDA graph, at the price of decoding the points outside the boxes too.

The ablation variants of the supplementary (:data:`STRATEGIES`, a :class:`Ranking` each) also choose the training
points:
"absolute" (HOISDF) and "gradient" train on near-surface rows, "signed" on rows inside the meshes
(:func:`inside_rows`), "random" on random grid points inside the box (:func:`random_grid_points`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from hoisdf.model.encoding import project_points

SdfFn = Callable[[torch.Tensor], torch.Tensor]  # camera points (B, M, 3) -> scaled SDF (B, M)


def _signed(sdf: torch.Tensor) -> torch.Tensor:
    return sdf


@dataclass(frozen=True)
class Ranking:
    """How field-guided sampling orders the grid points inside a box.

    ``score``: scaled SDF (B, M) -> score (B, M), lowest first (None: uniformly random among the inside points,
    without decoding the grid); ``newton``: then one step onto the surface along the field's gradient.
    """

    score: Callable[[torch.Tensor], torch.Tensor] | None
    newton: bool = False


ABSOLUTE, SIGNED, RANDOM, GRADIENT = Ranking(torch.abs), Ranking(_signed), Ranking(None), Ranking(torch.abs, True)
STRATEGIES = {"absolute": ABSOLUTE, "signed": SIGNED, "random": RANDOM, "gradient": GRADIENT}
"""``model.sampling`` name -> its ranking: "absolute" smallest |SDF| (HOISDF), "signed" smallest SDF (deepest
inside), "random" uniformly among the inside points, "gradient" as "absolute" and then one step onto the surface."""


def noise_scale(progress: float, ratios: tuple[float, ...] = (0.3, 0.7),
                dists: tuple[float, ...] = (0.03, 0.05, 0.07)) -> float:
    """Noise half-width (scaled units) for the within-epoch progress in [0, 1]: dists[#ratios exceeded]."""
    return dists[sum(progress > r for r in ratios)]


def jitter(points: torch.Tensor, half_width: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """points (B, N, 3) + per-coordinate uniform noise in [-half_width, half_width] (drawn on the CPU)."""
    noise = (torch.rand(points.shape, generator=generator, device="cpu") * 2 - 1) * half_width  # CPU generator
    return points + noise.to(points)


def grid_points(resolution: int, sheared: bool = False, device=None) -> torch.Tensor:
    """(resolution^3, 3) lattice over [-1, 1]^3 in scaled units, x slowest.

    ``sheared=True`` reproduces the reference code's lattice value for value (amathislab/HOISDF
    ``main/model.py::Model.sdf_infer``): its index arithmetic used true division on int64 indices, so with
    ``i = n^2 a + n b + c`` it computes, in float32, x = (i / n / n) % n, y = (i / n) % n, z = i % n, then
    ``* 2 / (n - 1) - 1``: x and y pick up fractions of the faster indices (both reach ~1.03). The same
    operations in the same dtype (on the CPU) give bit-identical values (tests/test_sampling.py).
    """
    n = resolution
    if sheared:
        i = torch.arange(n ** 3)  # int64, as the reference; float32 true division below
        idx = torch.stack([(i / n / n) % n, (i / n) % n, (i % n).float()], dim=1)
        return (idx * (2.0 / (n - 1)) + -1.0).to(device)
    idx = torch.arange(n ** 3, device=device, dtype=torch.float64)
    c = torch.remainder(idx, n)
    b = torch.remainder(torch.div(idx, n, rounding_mode="floor"), n)
    a = torch.div(idx, n * n, rounding_mode="floor")
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


def _rank(score: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, M) column order: valid columns by ascending score, then the invalid ones; ties keep column order."""
    masked = torch.where(valid, score, torch.full_like(score, float("inf")))
    return torch.sort(masked, dim=1, stable=True).indices


def _inside_grid(grid: torch.Tensor, center: torch.Tensor, scale: float, K: torch.Tensor, box: torch.Tensor,
                 chunk: int) -> torch.Tensor:
    """(B, G) bool: grid point g of sample b projects strictly inside box b."""
    return torch.cat([inside_box(grid[None, s:s + chunk] / scale + center[:, None], K, box)
                      for s in range(0, grid.shape[0], chunk)], dim=1)


def random_grid_points(grid: torch.Tensor, center: torch.Tensor, scale: float, K: torch.Tensor, box: torch.Tensor,
                       n: int, generator: torch.Generator | None = None, chunk: int = 32768) -> torch.Tensor:
    """(B, n, 3) scaled grid points drawn uniformly (without replacement) among those inside each box.

    The scores are drawn for the whole grid (B, G) on the CPU, so the fixed-shape and the compact path see the
    same draw. Shapes as :func:`field_guided_points`.
    """
    grid = grid.to(center.dtype)
    with torch.no_grad():
        inside = _inside_grid(grid, center, scale, K, box, chunk)
        score = torch.rand(inside.shape, generator=generator).to(device=inside.device, dtype=grid.dtype)
        return grid[_rank(score, inside)[:, :n]]


def inside_rows(points: torch.Tensor, sdf: torch.Tensor, n: int,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, n, 3): ``n`` of the SDF rows (B, M, 3) whose own signed distance (B, M) is negative (inside the mesh),
    drawn uniformly with replacement on the CPU; a sample without such a row takes its smallest-SDF row."""
    inside = (sdf < 0).float()
    deepest = torch.nn.functional.one_hot(sdf.argmin(dim=1), sdf.shape[1]).to(inside)
    weights = torch.where(inside.sum(1, keepdim=True) > 0, inside, deepest)
    idx = torch.multinomial(weights.detach().cpu(), n, replacement=True, generator=generator).to(points.device)
    return torch.gather(points, 1, idx[..., None].expand(-1, -1, points.shape[-1]))


def _grid_sdf(points: torch.Tensor, center: torch.Tensor, scale: float, sdf_fn: SdfFn, chunk: int) -> torch.Tensor:
    """(B, M) SDF of scaled points (B, M, 3) or (1, M, 3) in chunks of ``chunk`` columns."""
    return torch.cat([sdf_fn(points[:, s:s + chunk] / scale + center[:, None])
                      for s in range(0, points.shape[1], chunk)], dim=1)


def field_guided_points(grid: torch.Tensor, center: torch.Tensor, scale: float, K: torch.Tensor, box: torch.Tensor,
                        sdf_fn: SdfFn, n: int, strategy: Ranking = ABSOLUTE, chunk: int = 32768,
                        generator: torch.Generator | None = None, fixed_shape: bool = False,
                        newton_fn: SdfFn | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``n`` grid points per sample that the strategy ranks first among those inside the box.

    grid: (G, 3) scaled lattice (see :func:`grid_points`); center: (B, 3) camera-frame centre, metres;
    K: (B, 3, 3); box: (B, 4) in the same pixels as K; sdf_fn: camera points (B, M, 3) -> scaled SDF
    (B, M) of the field being sampled. ``strategy``: a :class:`Ranking` (:data:`STRATEGIES`): :data:`ABSOLUTE`
    smallest |SDF| (HOISDF), :data:`SIGNED` smallest SDF (deepest inside), :data:`RANDOM` uniformly among the
    inside points, :data:`GRADIENT` as absolute and then one step onto the surface along the field's gradient
    (``newton_fn``, default ``sdf_fn``: give one whose gradient flows through the image features too).
    ``fixed_shape``: decode the whole grid with the box as a mask (static shapes; the same points as the default
    compact path, see the module docstring).
    Returns (points (B, n, 3) scaled, relative to ``center``; sdf (B, n) scaled, from ``sdf_fn``).
    Runs without gradient, except the "gradient" step (which needs it for the points, not the weights).
    """
    B = center.shape[0]
    grid = grid.to(center.dtype)
    if strategy.score is None:
        points = random_grid_points(grid, center, scale, K, box, n, generator, chunk)
        with torch.no_grad():
            return points, sdf_fn(points / scale + center[:, None])
    with torch.no_grad():
        inside = _inside_grid(grid, center, scale, K, box, chunk)  # (B, G)
        if fixed_shape:
            cand, valid = grid[None], inside
        else:
            m = min(grid.shape[0], max(int(inside.sum(1).max()), n))
            order = torch.argsort((~inside).to(torch.uint8), dim=1, stable=True)[:, :m]  # inside points first
            cand, valid = grid[order], torch.gather(inside, 1, order)  # (B, m, 3), (B, m)
        sdf = _grid_sdf(cand, center, scale, sdf_fn, chunk)
        pick = _rank(strategy.score(sdf), valid)[:, :n]
        points = torch.gather(cand.expand(B, -1, -1), 1, pick[..., None].expand(B, n, 3))
        sdf = torch.gather(sdf, 1, pick)
    if strategy.newton:
        points, sdf = _newton_step(points, center, scale, newton_fn or sdf_fn)
    return points, sdf


def _newton_step(points: torch.Tensor, center: torch.Tensor, scale: float, sdf_fn: SdfFn):
    """Move each scaled point by -sdf * unit gradient of ``sdf_fn`` (one projection step onto the zero level set)."""
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        sdf = sdf_fn(p / scale + center[:, None])
        (grad,) = torch.autograd.grad(sdf.sum(), p)
    unit = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    moved = (p - sdf[..., None] * unit).detach()
    with torch.no_grad():
        return moved, sdf_fn(moved / scale + center[:, None])
