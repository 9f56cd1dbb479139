"""Train sg-feature-splat on the synthetic reference capture on CPU and report held-out quality.

    python -m sg_nerfstudio.bench.feature_splat [--scene DIR] [--steps 4000] [--output DIR]

Builds the default synthetic scene when `--scene` is not given, trains with the offline teacher on the
CPU, then evaluates every held-out reference view (nerfstudio's colmap eval split: every 8th image):
PSNR of the RGB render and the mean cosine similarity between decoded and teacher features on the
teacher grid. Prints one table with the wall time of each phase. Goal on a 2-core machine:
PSNR >= 24 dB and mean cosine >= 0.8 within 15 minutes.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.synthetic import PRESETS, generate_scene
from sg_nerfstudio.splat.training import cpu_config, save, train


@dataclass
class Args:
    scene: Optional[Path] = None
    """A scene from sg-make-scene; default: generate the default preset into the output directory."""
    output: Optional[Path] = None
    """Where the scene, feature cache and checkpoint go; default: a temporary directory."""
    steps: int = 4000
    """Training steps."""
    resolution_schedule: int = 500
    """Steps per resolution doubling (splatfacto: 3000, for 30k-step GPU runs)."""
    teacher_input_size: int = 256
    """Offline teacher input size (grid = size / 8)."""
    threads: Optional[int] = None
    log_every: int = 250
    """Print progress every this many steps."""
    feature_dim: int = 128
    """Per-Gaussian feature length (paper: 128)."""
    stop_split_at: int = 1200
    """Last densification step (splatfacto: 15000); bounds the Gaussian count, hence the CPU step time."""
    background_color: str = "learned"
    """learned (one RGB colour optimised with the model: the synthetic sky is a smooth gradient that
    Gaussians initialised from SfM points never cover), random (splatfacto's default), black or white."""


def view_quality(pipeline, split: str) -> tuple[int, float, float]:
    """(views, mean PSNR dB, mean feature cosine on the teacher grid) over the split's cached images."""
    datamanager, model = pipeline.datamanager, pipeline.model
    dataset, cached = (datamanager.train_dataset, datamanager.cached_train) if split == "train" else (datamanager.eval_dataset, datamanager.cached_eval)
    psnrs, cosines = [], []
    for index in range(len(dataset)):
        camera = dataset.cameras[index : index + 1].to(model.device)
        metrics, _ = model.get_image_metrics_and_images(model.get_outputs_for_camera(camera), cached[index])
        psnrs.append(metrics["psnr"])
        cosines.append(metrics["feature_cosine"])
    if not psnrs:
        return 0, float("nan"), float("nan")
    return len(psnrs), statistics.mean(psnrs), statistics.mean(cosines)


def run(args: Args) -> dict:
    args.threads = set_threads(args.threads)
    console = Console(width=120)
    output = args.output or Path(tempfile.mkdtemp(prefix="sg_bench_feature_splat_"))
    timings = {}
    start = time.perf_counter()
    scene = args.scene
    if scene is None:
        scene = output / "scene"
        if not scene.exists():
            generate_scene(PRESETS["default"], scene)
    timings["scene"] = time.perf_counter() - start

    teacher = TeacherConfig(name="offline", input_size=args.teacher_input_size, cache_dir=output / "feature_cache")
    config = cpu_config(scene / "reference", output / "runs", args.steps, teacher, experiment_name="reference")
    config.pipeline.model.resolution_schedule = args.resolution_schedule
    config.pipeline.model.feature_dim = args.feature_dim
    config.pipeline.model.stop_split_at = args.stop_split_at
    config.pipeline.model.background_color = args.background_color

    start = time.perf_counter()

    def log(step: int, trainer, _losses) -> None:
        if step % args.log_every == 0:
            console.print(f"step {step}: {trainer.pipeline.model.num_points} Gaussians, {time.perf_counter() - start:.0f} s")

    trainer = train(config, log)
    timings["setup + training"] = time.perf_counter() - start
    save(trainer, config)

    start = time.perf_counter()
    pipeline = trainer.pipeline
    pipeline.eval()
    views, psnr, cosine = view_quality(pipeline, "eval")
    timings["evaluation"] = time.perf_counter() - start

    result = {
        "held_out_views": views,
        "psnr": psnr,
        "feature_cosine": cosine,
        "gaussians": pipeline.model.num_points,
        "steps": args.steps,
        "timings": timings,
        "config": str(config.get_base_dir() / "config.yml"),
    }
    table = Table(title=f"sg-feature-splat on {scene / 'reference'} (CPU, offline teacher, {args.steps} steps)")
    for column in ("held-out views", "PSNR (dB)", "feature cosine", "Gaussians", "train s", "total s", "goal"):
        table.add_column(column, justify="right")
    total = sum(timings.values())
    met = result["psnr"] >= 24 and result["feature_cosine"] >= 0.8 and total <= 900
    table.add_row(
        str(views), f"{result['psnr']:.2f}", f"{result['feature_cosine']:.3f}", str(result["gaussians"]),
        f"{timings['setup + training']:.0f}", f"{total:.0f}", "met" if met else "MISSED (PSNR>=24, cos>=0.8, <=900 s)",
    )
    console.print(table)
    console.print("Phase times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    console.print(f"Trained config: {result['config']}")
    return result


def entrypoint() -> None:
    sys.exit(cli_main(lambda: run(cli.parse(Args)) or 0))


if __name__ == "__main__":
    entrypoint()
