"""Speed of the CPU rasterizer: forward and forward+backward milliseconds per camera.

    python -m sg_nerfstudio.bench.rasterizer [--repeats 5] [--threads 2]

Scenes are the synthetic landmark (surface Gaussians like a trained splat) seen from a reference-ring
camera, with 131 channels (3 RGB + 128 features) of random colour. Cases:

- 20k Gaussians at 64x64, also with the dense brute-force compositor (speed ratio in the same run);
- 100k Gaussians at 128x128.

For each CPU backend ("numba" tile compositor, the default; "torch" pure-torch pair compositor):
forward, forward+backward with gradients for every Gaussian parameter and the pose, and forward+backward
for the pose only (what registration needs). Times are medians over `--repeats` runs after one warm-up
(which also loads numba's compiled kernels); goals on a 2-core machine: full forward+backward <= 150 ms
(case 1), <= 1.5 s (case 2).
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.render import rasterize
from sg_nerfstudio.render.cpu_rasterizer import brute_force_composite
from sg_nerfstudio.render.projection import covariances_from_quats_scales, project_gaussians
from sg_nerfstudio.synthetic.building import BuildingConfig, build_landmark
from sg_nerfstudio.synthetic.capture import look_at


@dataclass
class Args:
    repeats: int = 5
    """Timed runs per measurement (median reported), after one warm-up run."""
    threads: Optional[int] = None
    """CPU threads of torch and numba (default: the cores this process may use)."""
    channels: int = 131
    """Colour channels rendered."""


def landmark_case(n_gaussians: int, size: int, channels: int, seed: int = 0) -> dict:
    scene = build_landmark(BuildingConfig(n_gaussians=n_gaussians), seed=seed)
    pose = look_at(np.array([0.0, -45.0, 4.0]), np.array([0.0, 0.0, 8.0]))
    viewmat = torch.eye(4)
    viewmat[:3] = torch.from_numpy(pose.matrix()).float()
    focal = 0.5 * size / np.tan(np.deg2rad(31.0))
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    return {
        "means": torch.from_numpy(scene.means).float(),
        "quats": torch.from_numpy(scene.quats).float(),
        "scales": torch.from_numpy(scene.scales).float(),
        "opacities": torch.from_numpy(scene.opacities).float(),
        "colors": torch.rand(n_gaussians, channels, generator=gen),
        "viewmats": viewmat[None],
        "Ks": K[None],
        "width": size,
        "height": size,
    }


def timed(fn, repeats: int) -> tuple[float, float]:
    """Median (forward ms, backward ms) of `fn`, which returns its two phase durations in seconds."""
    fn()
    samples = [fn() for _ in range(repeats)]
    return tuple(1e3 * statistics.median(phase) for phase in zip(*samples))


def run_sparse(case: dict, grad_gaussians: bool, grad_pose: bool, backend: str) -> tuple[float, float]:
    params = {k: (case[k].clone().requires_grad_(grad_gaussians)) for k in ("means", "quats", "scales", "opacities", "colors")}
    pose = case["viewmats"].clone().requires_grad_(grad_pose)
    start = time.perf_counter()
    render, alpha, _ = rasterize(**params, viewmats=pose, Ks=case["Ks"], width=case["width"], height=case["height"], backend=backend)
    middle = time.perf_counter()
    if grad_gaussians or grad_pose:
        (render.mean() + alpha.mean()).backward()
    return middle - start, time.perf_counter() - middle


def run_dense(case: dict, backward: bool) -> tuple[float, float]:
    start = time.perf_counter()
    params = {k: case[k].clone().requires_grad_(backward) for k in ("means", "quats", "scales", "opacities", "colors")}
    pose = case["viewmats"].clone().requires_grad_(backward)
    covars = covariances_from_quats_scales(params["quats"], params["scales"])
    proj = project_gaussians(params["means"], covars, pose, case["Ks"], case["width"], case["height"])
    visible = proj.radii[0] > 0
    render, alpha = brute_force_composite(
        proj.means2d[0, visible], proj.conics[0, visible], params["opacities"][visible], params["colors"][visible],
        proj.depths[0, visible], case["width"], case["height"],
    )
    middle = time.perf_counter()
    if backward:
        (render.mean() + alpha.mean()).backward()
    return middle - start, time.perf_counter() - middle


def main(args: Args) -> None:
    args.threads = set_threads(args.threads)
    console = Console(width=150)
    table = Table(title=f"CPU rasterizer, ms per camera (median of {args.repeats}, {args.threads} threads, {args.channels} channels)")
    for column in ("case", "visible", "forward", "backward (all)", "backward (pose)", "fwd+bwd (all)", "fwd+bwd (pose)", "goal fwd+bwd (all)"):
        table.add_column(column, justify="right")
    cases = [("20k, 64x64", 20_000, 64, 150.0), ("100k, 128x128", 100_000, 128, 1500.0)]
    notes = []
    for label, n, size, goal in cases:
        case = landmark_case(n, size, args.channels)
        with torch.no_grad():
            _, _, info = rasterize(**case, backend="torch")
        visible = int((info["radii"] > 0).sum())
        for backend in ("numba", "torch"):
            forward, _ = timed(lambda: run_sparse(case, False, False, backend), args.repeats)
            full_fwd, full_bwd = timed(lambda: run_sparse(case, True, True, backend), args.repeats)
            pose_fwd, pose_bwd = timed(lambda: run_sparse(case, False, True, backend), args.repeats)
            full, pose = full_fwd + full_bwd, pose_fwd + pose_bwd
            verdict = "met" if full <= goal else "MISSED"
            table.add_row(
                f"{label} {backend}", f"{visible}", f"{forward:.1f}", f"{full_bwd:.1f}", f"{pose_bwd:.1f}", f"{full:.1f}",
                f"{pose:.1f}", f"<= {goal:.0f} ({verdict})",
            )
            notes.append(f"{label} {backend}: pose-only backward = {pose_bwd / full_bwd:.2f} x the full backward.")
            if backend == "numba":
                default_forward, default_full = forward, full
        if n == 20_000:
            dense_forward, _ = timed(lambda: run_dense(case, False), max(1, args.repeats // 2))
            dense_fwd, dense_bwd = timed(lambda: run_dense(case, True), max(1, args.repeats // 2))
            dense_full = dense_fwd + dense_bwd
            table.add_row("brute force", f"{visible}", f"{dense_forward:.1f}", f"{dense_bwd:.1f}", "-", f"{dense_full:.1f}", "-", "-")
            notes.append(
                f"Speed-up of the numba backend over the brute-force compositor ({label}): forward "
                f"x{dense_forward / default_forward:.1f}, forward+backward x{dense_full / default_full:.1f}."
            )
    console.print(table)
    for note in notes:
        console.print(note)


def entrypoint() -> None:
    sys.exit(cli_main(lambda: main(cli.parse(Args)) or 0))


if __name__ == "__main__":
    entrypoint()
