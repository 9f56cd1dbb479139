"""Reference training on CPU: today's full-resolution feature render against the teacher-grid-sized one.

    python -m sg_nerfstudio.bench.training --scenes DIR [DIR ...] [--steps 1500] [--scales 0 4]

For every scene (a directory as `sg-make-scene` writes it, synthetic or `--from-photos`: `reference/images`
and its COLMAP model) and every `feature_render_scale` (0: features rendered with the colour at the training
resolution, the path before this option existed; 4: the default) and every `--seeds` value it trains the
reference exactly as `sg-bench` does (`short_cpu_schedule`, offline teacher at 256 px, the colmap dataparser's
split: every 8th reference image held out), then reports wall time, Gaussians, PSNR and teacher-feature cosine
on the held-out and on the training views, and each arm's time as a ratio to the first scale's with the same
seed, all measured in this one run. Arms run one
after the other in this process, never side by side.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.bench.feature_splat import view_quality
from sg_nerfstudio.bench.layout import read_scene
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.splat.training import cpu_config, save, short_cpu_schedule, train

DEFAULT_SEED = 42
"""nerfstudio's machine.seed default."""


@dataclass
class Args:
    scenes: list[Path]
    """Scene directories (`sg-make-scene --output`), each trained once per scale."""
    steps: int = 1500
    """Training steps (sg-bench's default)."""
    scales: list[float] = field(default_factory=lambda: [0.0, 4.0])
    """feature_render_scale values to compare; the first is the baseline of the ratios."""
    output: Optional[Path] = None
    """Where feature caches and checkpoints go; default: a temporary directory."""
    threads: Optional[int] = None
    """torch and numba threads (default: the cores this process may use)."""
    log_every: int = 250
    """Print progress every this many steps."""
    seeds: list[int] = field(default_factory=lambda: [DEFAULT_SEED])
    """Training seeds (nerfstudio's machine.seed; 42 is its default); every scale trains once per seed."""


def train_arm(scene_dir: Path, scale: float, seed: int, steps: int, output: Path, console: Console, log_every: int) -> dict:
    """Train one reference as sg-bench does with this feature_render_scale; its time and quality."""
    scene = read_scene(scene_dir)
    name = f"{scene.name}-scale-{scale:g}-seed-{seed}"
    teacher = TeacherConfig(name="offline", input_size=256, cache_dir=output / "feature_cache")
    config = short_cpu_schedule(cpu_config(scene.reference, output / "runs", steps, teacher, experiment_name=name))
    config.pipeline.datamanager.dataparser.colmap_path = scene.reference_model
    config.pipeline.model.feature_render_scale = scale
    config.machine.seed = seed
    started = time.perf_counter()

    def log(step: int, trainer, _losses) -> None:
        if step % log_every == 0:
            console.print(f"{name} step {step}: {trainer.pipeline.model.num_points} Gaussians, {time.perf_counter() - started:.0f} s")

    trainer = train(config, log)
    elapsed = time.perf_counter() - started
    config_path = save(trainer, config)
    pipeline = trainer.pipeline
    pipeline.eval()
    held_out = view_quality(pipeline, "eval")
    training = view_quality(pipeline, "train")
    return {
        "scene": scene.name, "scale": scale, "seed": seed, "train_s": elapsed, "gaussians": pipeline.model.num_points,
        "held_out_views": held_out[0], "held_out_psnr": held_out[1], "held_out_cosine": held_out[2],
        "train_views": training[0], "train_psnr": training[1], "train_cosine": training[2], "config": str(config_path),
    }


def run(args: Args) -> list[dict]:
    threads = set_threads(args.threads)
    console = Console(width=140)
    output = args.output or Path(tempfile.mkdtemp(prefix="sg_bench_training_"))
    rows = [
        train_arm(scene, scale, seed, args.steps, output, console, args.log_every)
        for scene in args.scenes for seed in args.seeds for scale in args.scales
    ]
    console.print(training_table(rows, args.steps, threads))
    for row in rows:
        console.print(f"{row['scene']} scale {row['scale']:g} seed {row['seed']}: {row['config']}")
    return rows


def training_table(rows: list[dict], steps: int, threads: int) -> Table:
    """One row per arm; times as ratios to the first arm of the same scene and seed."""
    table = Table(title=f"Reference training, {steps} steps on CPU ({threads} threads)")
    for column in ("scene", "seed", "feature_render_scale", "train s", "vs first", "Gaussians", "held-out PSNR / cos", "train PSNR / cos"):
        table.add_column(column, justify="right")
    for row in rows:
        baseline = next(r for r in rows if r["scene"] == row["scene"] and r["seed"] == row["seed"])
        table.add_row(
            row["scene"], str(row["seed"]), f"{row['scale']:g}", f"{row['train_s']:.0f}", f"{row['train_s'] / baseline['train_s']:.2f}",
            str(row["gaussians"]), f"{row['held_out_psnr']:.2f} / {row['held_out_cosine']:.3f} ({row['held_out_views']})",
            f"{row['train_psnr']:.2f} / {row['train_cosine']:.3f} ({row['train_views']})",
        )
    return table


def entrypoint() -> None:
    sys.exit(cli_main(lambda: run(cli.parse(Args)) or 0))


if __name__ == "__main__":
    entrypoint()
