"""Grid-point features for field-guided sampling: direct sampling vs projecting the first layer first.

Usage: python -m bench.bench_grid_features [--points 60000] [--device cuda]

HOISDF's inference grid sends tens of thousands of points per image through ``sdf_in`` (Linear over the
concatenated pyramid features). Direct: sample all sum(C) pyramid channels per point, then the matrix
product. Projected (``hoisdf.model.encoding.project_pyramid``): a 1x1 convolution of each level by its
block of the first layer's weight, then sample levels x width channels and add. Both give the same
values (bilinear sampling is linear); which is faster depends on sum(C) against levels x width. The
model picks the projected path when it samples fewer channels (the "big" decoder).
"""

from __future__ import annotations

import argparse
import time

import torch

from hoisdf.model.encoding import project_pyramid, sample_projected, sample_pyramid

DECODERS = {"small (ResNet-50)": [32, 64, 128, 256, 512], "big (ResNet-50)": [128, 256, 512, 1024, 2048]}


def timed(fn, device: torch.device, reps: int) -> float:
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    for _ in range(reps):
        out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return (time.perf_counter() - start) / reps, out


@torch.no_grad()
def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--points", type=int, default=60000, help="grid points inside the box (one image)")
    p.add_argument("--size", type=int, default=256, help="input image side; the finest level is half of it")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args()
    device = torch.device(args.device)
    torch.manual_seed(0)
    print(f"device {device}, {args.points} points, width 512")
    print(f"{'decoder':>18} {'sum C':>6} {'direct ms':>10} {'projected ms':>13} {'speed-up':>9} {'max diff':>9}")
    for name, channels in DECODERS.items():
        pyramid = [torch.randn(1, c, args.size // 2 ** (i + 1), args.size // 2 ** (i + 1), device=device)
                   for i, c in enumerate(channels)]
        linear = torch.nn.Linear(sum(channels), 512).to(device)
        grid = torch.rand(1, args.points, 2, device=device) * 2 - 1
        t_direct, a = timed(lambda p=pyramid, g=grid, f=linear: f(sample_pyramid(p, g)), device, args.reps)
        t_proj, b = timed(lambda p=pyramid, g=grid, f=linear: sample_projected(project_pyramid(p, f), g, f.bias),
                          device, args.reps)
        print(f"{name:>18} {sum(channels):>6} {t_direct * 1e3:>10.0f} {t_proj * 1e3:>13.0f} "
              f"{t_direct / t_proj:>8.2f}x {float((a - b).abs().max()):>9.1e}")


if __name__ == "__main__":
    main()
