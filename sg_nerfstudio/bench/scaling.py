"""Registration cost at the size of real references: time per step and peak memory against the model's size.

    python -m sg_nerfstudio.bench.scaling --load-config <sg-feature-splat config.yml> \\
        --meta-image <scene>/meta/front [--sizes 100000 300000 1000000] [--device cpu|cuda] \\
        [--training-scene <sg-make-scene output>]

Real references hold 0.5-5 million Gaussians; the synthetic ones this project trains on a CPU hold tens of
thousands. The benchmark therefore *densifies* the given trained model to each size and writes it as a real
checkpoint (a copy of the run whose `step-*.ckpt` holds the larger model): every Gaussian is split into k
children drawn from its own distribution (means ~ N(mu, (1 - s^2) Sigma), covariance s^2 Sigma with
s = k^(-1/3), same opacity, colours and features), which keeps the model's look and puts k times as many
Gaussians, each smaller, on the same surfaces, as training a real landmark longer would.

Per size, in a fresh process each (so that peak memory is that size's alone), for today's path (cull only,
`--level-of-detail 0`, autograd projection) and the new path (the preset's `level_of_detail` and the compiled
frozen-model kernels):
- load: `load_reference` of the densified checkpoint (s);
- prepare: the first cull (and merge) around the start (s), the Gaussians a step then renders and the voxel
  (render pixels) they were merged at (the level of detail, doubled where the render budget asks for it);
- step: median wall time of `--steps` forward renders of every photo + the pose-only backward;
- peak resident memory of the process (ru_maxrss);
- with `--register`: a whole registration (the preset's steps, 5° / 0.1 / 10% start, verdict included) on
  the new path: wall time, ΔR / ΔT against the meta-image's `gt_transform.json`. With `--anchors` (the default)
  it registers as `ns-register-meta` and `sg-demo` do: with the keypoint anchors of the SIFT initialiser built
  from the reference's own COLMAP model and images (their time is recorded apart, `anchors_s`, the first time
  including the reference's SIFT cloud, which is then cached); on sg-demo's reference and its front meta-image,
  seed 0, this is the demo's own registration of that meta-image, from the same start.

Then `--concurrency`: the same registration of the base model twice at once and once alone, each process
with the default `--threads` (the cores this process may use): each concurrent run's time over the solo one.

Then, with `--training-scene`, reference training in the same run (`bench.training`: `--training-steps` of the
scene's reference, today's full-resolution feature render against the default, in this process after the others).

Everything is printed as tables (ratios to today's path in the same run), closed by one table of the figures
the issue "Registration at the size of real references" sets goals for, and written to `--output` (JSON).
Run it alone on the machine: other jobs change every figure.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.errors import InputError, cli_main

MODES = {"today": (0.0, False), "new": (None, True)}
"""Benchmark paths by name: the `level_of_detail` each runs with (None: the preset's) and whether the compiled
frozen-model kernels (`render.frozen_projection`) project and colour the model. `today` is the path before either
existed."""


@dataclass
class Args:
    load_config: Path
    """config.yml of the trained sg-feature-splat to densify."""
    meta_image: Path
    """A meta-image directory with `gt_transform.json` (e.g. sg-demo's scene/meta/front)."""
    sizes: tuple[int, ...] = (100_000, 300_000, 1_000_000)
    """Gaussians of the densified references."""
    config: str = "fast-cpu"
    """Registration preset (name or YAML)."""
    level_of_detail: Optional[float] = None
    """The new path's level of detail in render pixels (default: the preset's)."""
    render_budget: Optional[int] = None
    """The new path's render budget in Gaussians (default: the preset's; 0: none)."""
    steps: int = 5
    """Timed steps per size and path (the first, which builds the cull, is not among them)."""
    register: bool = True
    """Also run whole registrations: both paths on the model as trained, the new path per size."""
    anchors: bool = True
    """Whole registrations with the SIFT keypoint anchors, as ns-register-meta registers (--no-anchors: the dense
    objective alone)."""
    concurrency: bool = True
    training_scene: Optional[Path] = None
    """Also train this scene's reference (`sg-make-scene` layout) with both feature render paths (bench.training)."""
    training_steps: int = 1500
    device: Literal["cpu", "cuda"] = "cpu"
    threads: Optional[int] = None
    """Threads of each process (default: the cores it may use)."""
    work_dir: Optional[Path] = None
    """Where the densified runs are written (default: a temporary directory, removed at the end)."""
    output: Path = Path("benchmark_scaling.json")
    seed: int = 0


@dataclass
class ChildArgs:
    """One measurement in its own process (the benchmark runs itself with `child`)."""

    load_config: Path
    meta_image: Path
    config: str = "fast-cpu"
    level_of_detail: Optional[float] = None
    """None: the preset's."""
    render_budget: Optional[int] = None
    """None: the preset's."""
    frozen_kernels: bool = True
    steps: int = 5
    register: bool = False
    anchors: bool = False
    """Register with the keypoint anchors of the reference's SIFT initialiser."""
    device: str = "cpu"
    threads: Optional[int] = None
    seed: int = 0


def densify_run(config_path: Path, gaussians: int, target: Path, seed: int) -> Path:
    """A copy of the trained run at `config_path` whose checkpoint holds `gaussians` Gaussians (module docstring)."""
    from sg_nerfstudio.splat.trained import open_trained_run, read_checkpoint

    run = open_trained_run(config_path)
    state = read_checkpoint(run.checkpoints[-1])
    prefix = "_model.gauss_params."
    params = {key[len(prefix):]: value for key, value in state["pipeline"].items() if key.startswith(prefix)}
    count = params["means"].shape[0]
    generator = torch.Generator().manual_seed(seed)
    children = torch.full((count,), gaussians // count, dtype=torch.long)
    children[torch.randperm(count, generator=generator)[: gaussians % count]] += 1
    parent = torch.repeat_interleave(torch.arange(count), children)
    shrink = children.double().pow(-1.0 / 3.0)[parent]  # s = k^(-1/3) per child
    from sg_nerfstudio.render.projection import quat_to_rotmat

    scales = torch.exp(params["scales"].double())[parent]
    rotations = quat_to_rotmat(params["quats"].double())[parent]
    spread = torch.sqrt((1.0 - shrink**2).clamp(min=0.0))[:, None] * scales
    offsets = (rotations @ (spread * torch.randn(parent.shape[0], 3, generator=generator, dtype=torch.float64))[:, :, None])[:, :, 0]
    dense = {name: value[parent].clone() for name, value in params.items()}
    dense["means"] = (params["means"].double()[parent] + offsets).to(params["means"].dtype)
    dense["scales"] = torch.log(scales * shrink[:, None]).to(params["scales"].dtype)
    pipeline = {key: value for key, value in state["pipeline"].items() if not key.startswith(prefix)}
    pipeline.update({prefix + name: value for name, value in dense.items()})
    target.mkdir(parents=True, exist_ok=True)
    shutil.copy2(run.config_path, target / "config.yml")
    shutil.copy2(run.config_path.parent / "dataparser_transforms.json", target / "dataparser_transforms.json")
    model_dir = target / run.config.relative_model_dir
    model_dir.mkdir(parents=True, exist_ok=True)
    torch.save({"step": state["step"], "pipeline": pipeline}, model_dir / run.checkpoints[-1].name)
    return target / "config.yml"


def measure(args: ChildArgs) -> dict:
    """Load, cull, time steps and optionally register (see the module docstring); runs in its own process."""
    from sg_nerfstudio.geometry.meta_image import load_meta_image
    from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
    from sg_nerfstudio.initialisers.pipeline import reference_keypoints
    from sg_nerfstudio.registration.metrics import pose_errors
    from sg_nerfstudio.registration.objectives import PhotoLosses, build_objective, prepare_photos
    from sg_nerfstudio.registration.optimize import effective_near_plane, register
    from sg_nerfstudio.registration.reference import load_reference
    from sg_nerfstudio.registration.session import resolve_device
    from sg_nerfstudio.registration.settings import load_preset
    from sg_nerfstudio.render.threads import set_threads

    from sg_nerfstudio.render import rasterization

    rasterization.FROZEN_KERNELS = args.frozen_kernels
    threads = set_threads(args.threads)
    settings = load_preset(args.config).changed(seed=args.seed)
    if args.level_of_detail is not None:
        settings = settings.changed(level_of_detail={"voxel_pixels": args.level_of_detail})
    if args.render_budget is not None:
        settings = settings.changed(level_of_detail={"render_budget": args.render_budget})
    started = time.perf_counter()
    reference = load_reference(args.load_config, device=resolve_device(args.device))
    loaded = time.perf_counter() - started
    meta = load_meta_image(args.meta_image)
    truth = Sim3.read_json(args.meta_image / "gt_transform.json", "Ground truth")
    start = perturbed(truth, meta.centres, np.random.default_rng(args.seed), 5.0, 0.1, 0.1)
    objective = build_objective(reference, settings)
    photos = prepare_photos(reference, meta, settings, objective)
    start_ns = reference.world_to_dataparser @ start
    losses = PhotoLosses(reference, photos, objective, settings, effective_near_plane(meta, start_ns, settings.objective.near_plane))
    centre = torch.from_numpy(meta.centroid_under(start_ns))
    everything = list(range(len(photos)))

    def step() -> float:
        began = time.perf_counter()
        delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
        values, _ = losses(Sim3.update(delta, centre) @ start_ns.to_torch(), everything)
        torch.stack(values).mean().backward()
        if args.device == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - began

    began = time.perf_counter()
    losses.visible.for_pose(start_ns)
    prepared = time.perf_counter() - began
    step()  # warm-up: first calls of the compiled kernels
    times = [step() for _ in range(args.steps)]
    record = {
        "gaussians": reference.count, "rendered": losses.visible.subset.count, "level_of_detail": settings.level_of_detail.voxel_pixels,
        "render_budget": settings.level_of_detail.render_budget, "voxel_pixels": losses.visible.voxel_pixels,
        "frozen_kernels": args.frozen_kernels,
        "threads": threads, "load_s": loaded, "prepare_s": prepared, "step_s": statistics.median(times),
        "photos": len(photos), "render_size": [photos[0].width, photos[0].height],
    }
    if args.register:
        keypoints = None
        if args.anchors:
            began = time.perf_counter()
            keypoints = reference_keypoints(args.load_config, meta)
            record.update(anchors_s=time.perf_counter() - began, anchored_photos=len(keypoints))
        result = register(reference, meta, start, settings, photos=photos, objective=objective, keypoints=keypoints)
        errors = pose_errors(meta.poses, result.transform, truth)
        before = pose_errors(meta.poses, start, truth)
        record.update(
            register_s=result.wall_time_s, dR_before=before.rotation_deg, dT_before=before.translation,
            dR=errors.rotation_deg, dT=errors.translation, verdict=result.verdict.label,
        )
    record["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    if args.device == "cuda":
        record["peak_cuda_gb"] = torch.cuda.max_memory_allocated() / 2**30
    return record


def run_child(child: ChildArgs, wait: bool = True):
    """Start `measure(child)` in a fresh Python process; its record (or the Popen when not `wait`)."""
    command = [sys.executable, "-m", "sg_nerfstudio.bench.scaling", "child", "--load-config", str(child.load_config),
               "--meta-image", str(child.meta_image), "--config", child.config,
               "--frozen-kernels" if child.frozen_kernels else "--no-frozen-kernels",
               "--steps", str(child.steps), "--device", child.device, "--seed", str(child.seed)]
    command += ["--register"] if child.register else ["--no-register"]
    command += ["--anchors"] if child.anchors else ["--no-anchors"]
    command += ["--threads", str(child.threads)] if child.threads else []
    command += ["--level-of-detail", str(child.level_of_detail)] if child.level_of_detail is not None else []
    command += ["--render-budget", str(child.render_budget)] if child.render_budget is not None else []
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    return read_record(process) if wait else process


class MeasurementFailed(InputError):
    """A measurement process that stopped (its own sentence or traceback is printed above it)."""


def read_record(process: subprocess.Popen) -> dict:
    out, _ = process.communicate()
    if process.returncode != 0:
        raise MeasurementFailed(f"A measurement process stopped (exit {process.returncode}); what stopped it is printed above.")
    return json.loads(out.strip().splitlines()[-1])


def growth(args: Args, work: Path, console: Console) -> list[dict]:
    """Both paths on the model as trained (size 0 in the records), then on each densified size."""
    rows = []
    for size in (0, *args.sizes):
        console.print(f"[bold]{f'{size:,} Gaussians' if size else 'the model as trained'}[/bold]")
        config = densify_run(args.load_config, size, work / f"dense-{size}", args.seed) if size else args.load_config
        for mode, (level, kernels) in MODES.items():
            level = args.level_of_detail if level is None else level
            whole = args.register and (mode == "new" or not size)  # today's path registers 1M Gaussians in hours
            budget = args.render_budget if mode == "new" else None
            child = ChildArgs(config, args.meta_image, args.config, level, budget, kernels, args.steps, whole, args.anchors, args.device, args.threads, args.seed)
            record = {"size": size, "mode": mode, **run_child(child)}
            console.print(record)
            rows.append(record)
        if size:
            shutil.rmtree(work / f"dense-{size}")
    return rows


def growth_table(rows: list[dict], console: Console) -> None:
    table = Table(title="Cost per step against the reference's size (ratios: to today's path at the same size / to the smallest densified size)")
    for column in ("Gaussians", "path", "voxel px (LOD / budget)", "rendered", "load s", "prepare s", "step s", "vs today", "vs smallest", "peak GB", "register s", "ΔR° / ΔT", "verdict"):
        table.add_column(column, justify="right")
    today = {row["size"]: row["step_s"] for row in rows if row["mode"] == "today"}
    smallest_size = min(r["size"] for r in rows if r["size"]) if any(r["size"] for r in rows) else 0
    smallest = {row["mode"]: row["step_s"] for row in rows if row["size"] == smallest_size}
    for row in rows:
        registered = "register_s" in row
        table.add_row(
            f"{row['gaussians']:,}", row["mode"], voxel_label(row), f"{row['rendered']:,}", f"{row['load_s']:.1f}", f"{row['prepare_s']:.2f}",
            f"{row['step_s']:.3f}", f"{row['step_s'] / today[row['size']]:.2f}", f"{row['step_s'] / smallest[row['mode']]:.2f}",
            f"{row['peak_rss_gb']:.1f}", register_label(row) if registered else "-",
            f"{row['dR']:.2f} / {row['dT']:.3f}" if registered else "-", row.get("verdict", "-"),
        )
    console.print(table)


def register_label(row: dict) -> str:
    """register() wall time, with the keypoint anchors' extraction and matching after it where they ran."""
    return f"{row['register_s']:.1f}" + (f" (+{row['anchors_s']:.0f} anchors)" if "anchors_s" in row else "")


def voxel_label(row: dict) -> str:
    """The voxel a row's render merged at, with the preset's level of detail and render budget behind it."""
    if not row["level_of_detail"]:
        return "off"
    budget = f"{row['render_budget'] / 1000:g}k" if row.get("render_budget") else "none"
    return f"{row.get('voxel_pixels', row['level_of_detail']):g} ({row['level_of_detail']:g} / {budget})"


def concurrency(args: Args, console: Console) -> dict:
    """The base model's registration alone, then two at once (each with the default threads)."""
    child = ChildArgs(args.load_config, args.meta_image, args.config, args.level_of_detail, args.render_budget, True, 1, True, args.anchors, args.device, args.threads, args.seed)
    solo = run_child(child)
    pair = [run_child(child, wait=False) for _ in range(2)]
    together = [read_record(process) for process in pair]
    table = Table(title=f"Two registrations at once ({together[0]['threads']} threads each) vs one alone")
    for column in ("run", "register s", "x solo"):
        table.add_column(column, justify="right")
    table.add_row("alone", f"{solo['register_s']:.1f}", "1.00")
    for index, record in enumerate(together):
        table.add_row(f"concurrent {index + 1}", f"{record['register_s']:.1f}", f"{record['register_s'] / solo['register_s']:.2f}")
    console.print(table)
    return {"solo": solo, "concurrent": together}


def training(args: Args, work: Path, console: Console) -> list[dict]:
    """`bench.training` of `--training-scene`: today's feature render (scale 0) then the default (4), one after the
    other in this process, after every measurement process has ended."""
    from sg_nerfstudio.bench.training import DEFAULT_SEED, train_arm, training_table
    from sg_nerfstudio.render.threads import set_threads

    threads = set_threads(args.threads)
    rows = [train_arm(args.training_scene, scale, DEFAULT_SEED, args.training_steps, work / "training", console, 250) for scale in TRAINING_SCALES]
    console.print(training_table(rows, args.training_steps, threads))
    return rows


TRAINING_SCALES = (0.0, 4.0)
"""feature_render_scale of today's training path (features at the training resolution) and of the default."""


def goals_table(report: dict, console: Console) -> None:
    """The issue's goals next to what this run measured (rows only for the parts that ran)."""
    table = Table(title="Goals of the issue \"Registration at the size of real references\", as measured in this run")
    for column in ("goal", "new path", "today's path", "met"):
        table.add_column(column)
    rows = report["growth"]
    base = {row["mode"]: row for row in rows if row["size"] == 0}
    if "register_s" in base.get("new", {}):
        today = f"{base['today']['register_s']:.1f} s" if "register_s" in base.get("today", {}) else "-"
        new = base["new"]["register_s"]
        table.add_row(f"registration of the meta-image against the model as trained ({base['new']['photos']} photos, {base['new']['gaussians']:,} Gaussians) <= 60 s",
                      f"{new:.1f} s", today, yes(new <= 60.0))
    sizes = sorted({row["size"] for row in rows if row["size"]})
    if len(sizes) > 1:
        step = {(row["size"], row["mode"]): row for row in rows}
        growth_of = lambda mode: step[(sizes[-1], mode)]["step_s"] / step[(sizes[0], mode)]["step_s"]  # noqa: E731
        table.add_row(f"step at {sizes[-1]:,} <= 3x step at {sizes[0]:,}", f"{growth_of('new'):.2f}x", f"{growth_of('today'):.2f}x", yes(growth_of("new") <= 3.0))
        largest = step[(sizes[-1], "new")]
        what = "register" if "register_s" in largest else "step"
        table.add_row(f"{sizes[-1]:,} Gaussians {what} within 24 GB (peak resident)", f"{largest['peak_rss_gb']:.1f} GB", f"{step[(sizes[-1], 'today')]['peak_rss_gb']:.1f} GB (step)", yes(largest["peak_rss_gb"] <= 24.0))
    if "concurrency" in report:
        worst = max(record["register_s"] for record in report["concurrency"]["concurrent"]) / report["concurrency"]["solo"]["register_s"]
        table.add_row("two registrations at once: each <= about 2x its solo time", f"{worst:.2f}x (the slower)", "-", yes(worst <= 2.0))
    if "training" in report:
        today_arm, new_arm = report["training"]
        steps = report["args"]["training_steps"]
        table.add_row(f"training {steps} steps of {today_arm['scene']} <= 10 min", f"{new_arm['train_s'] / 60:.1f} min", f"{today_arm['train_s'] / 60:.1f} min", yes(new_arm["train_s"] <= 600.0))
        difference = lambda key: new_arm[key] - today_arm[key]  # noqa: E731
        table.add_row("... same PSNR (held-out / training views, dB)", f"{new_arm['held_out_psnr']:.2f} / {new_arm['train_psnr']:.2f}",
                      f"{today_arm['held_out_psnr']:.2f} / {today_arm['train_psnr']:.2f}", f"{difference('held_out_psnr'):+.2f} / {difference('train_psnr'):+.2f} dB")
    console.print(table)


def yes(condition: bool) -> str:
    return "yes" if condition else "no"


def main(args: Args) -> None:
    console = Console(width=160)
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="sg-scaling-"))
    report: dict = {"args": {key: str(value) for key, value in vars(args).items()}, "cpu_count": os.cpu_count()}
    try:
        report["growth"] = growth(args, work, console)
        growth_table(report["growth"], console)
        if args.concurrency:
            report["concurrency"] = concurrency(args, console)
        if args.training_scene is not None:
            report["training"] = training(args, work, console)
        goals_table(report, console)
    finally:
        if args.work_dir is None:
            shutil.rmtree(work, ignore_errors=True)
    args.output.write_text(json.dumps(report, indent=2, default=float))
    console.print(f"Raw results: {args.output}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "child":
        sys.exit(cli_main(lambda: print(json.dumps(measure(cli.parse(ChildArgs, args=sys.argv[2:])), default=float)) or 0))
    sys.exit(cli_main(lambda: main(cli.parse(Args)) or 0))
