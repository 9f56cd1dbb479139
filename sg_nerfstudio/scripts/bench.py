"""`sg-bench`: the in-the-wild benchmark on a directory of scenes, with the paper's tables.

    sg-make-scene --preset benchmark --output bench
    sg-bench bench --output bench-results [--initialisers colmap generalized perturbed] \\
        [--ablations full photometric l2 none outlier-lts fixed-lts irls] [--noise-levels 2 5 10 15 20] [--sizes 3 6 10]

For each scene (layout: sg_nerfstudio/bench/layout.py): train an sg-feature-splat reference on CPU with the
offline teacher (or reuse one from an earlier run), then for each meta-image run each initialiser and our
registration from its start, plus ablations and robustness runs on request (sg_nerfstudio/bench/runs.py).
Writes `<output>/results.md` and `results.csv` (Table 1 layout, threshold sweeps, per-meta-image breakdown,
ablations) and PNG robustness curves (bench/report.py). Resumable: run the same command again after an
interruption and finished references and runs are reused. Several benchmark directories are run as one suite
(`sg-bench gap-benchmark gap-real --output gap-results`: synthetic and real-photo scenes in one table).

    sg-bench teacher PAIRS --output OUT [--teachers colour offline dense-sift hog-layout] [--dinov2-weights W]

The teacher benchmark (bench/teacher.py) on photo/render pairs at a known pose (layout: bench/pairs.py).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Optional

import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sg_nerfstudio import cli
from sg_nerfstudio.atomic import OutputPathError, atomic_directory, check_apart_from_inputs, check_new_output_directory, check_output_path, output_lock
from sg_nerfstudio.bench.gap import benchmark_gap, gap_sentence
from sg_nerfstudio.bench.layout import BenchmarkLayoutError, read_benchmark, read_benchmarks
from sg_nerfstudio.bench.pairs import read_pairs
from sg_nerfstudio.bench.report import write_results
from sg_nerfstudio.bench.teacher import BASELINE, build_describers, run_pairs
from sg_nerfstudio.bench.teacher_report import landscape_figure, summarise, write_report
from sg_nerfstudio.bench.runs import ABLATIONS, BenchOptions, SceneRunner, read_records, train_reference
from sg_nerfstudio.bench.twins import TwinSceneRunner, build_twins
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.initialisers import set_colmap_verbosity
from sg_nerfstudio.registration.optimize import total_steps
from sg_nerfstudio.registration.settings import PRESETS, load_preset
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.errors import cli_main

Start = Literal["colmap", "generalized", "dense", "auto", "perturbed"]
Ablation = Literal[tuple(ABLATIONS)]  # type: ignore[valid-type]
BenchTeacher = Literal[BASELINE, "offline", "dense-sift", "hog-layout", "dinov2"]  # type: ignore[valid-type]


@dataclass
class BenchArgs:
    """Run the benchmark on every scene of one or more benchmark directories and write results.md / results.csv. (The teacher
    benchmark on photo/render pairs: `sg-bench teacher --help`.)"""

    benchmarks: Annotated[tuple[Path, ...], tyro.conf.Positional]
    """Benchmark directories (e.g. from `sg-make-scene --preset benchmark`); several are run as one suite, their
    scenes side by side in one table (every scene name must differ), e.g. the synthetic and the real-photo gap scenes."""
    output: Path
    """Results, trained references and per-run records; reused when the command is run again."""
    config: str = "fast-cpu"
    """Registration preset: a name (paper, fast-cpu, fast-cpu-features, wide-cpu) or a YAML file."""
    train_steps: int = 1500
    """Training steps of each reference model (CPU, offline teacher); 1500 trains each reference of the default
    suite in under 2 minutes on a 2-core CPU (93-107 s measured; the demo and the feature benchmark train 3000)."""
    initialisers: tuple[Start, ...] = ("colmap", "generalized")
    """Starts of Table 1: the SIFT + pycolmap initialisers (the paper's rows); `dense` (no SIFT: teacher maps) and
    `auto` (colmap, generalized, then dense); add `perturbed` for the ground truth moved by 5° / 0.1 / 10% (a start
    that does not depend on SIFT; one more registration per meta-image)."""
    ablations: tuple[Ablation, ...] = ()
    """Ablation rows to run from the perturbed start (e.g. full photometric l2 none outlier-lts fixed-lts irls)."""
    noise_levels: tuple[float, ...] = ()
    """Rotation noise (degrees) of extra starts from the ground truth, with translation and scale noise in
    proportion (30°: 0.5 scene units and 30%): the noise table and the curve of final error vs initial noise. 0 starts
    at the ground truth itself: where registration ends from a perfect start, on the reference's own objective."""
    noise_samples: int = 1
    """Random start directions per noise level and meta-image."""
    compare_config: tuple[str, ...] = ()
    """Other presets (names or YAML files) the noise runs are repeated with, from the same starts (e.g. wide-cpu)."""
    sizes: tuple[int, ...] = ()
    """Meta-image sizes (>= 3) of random photo subsets, for the curve of final error vs meta-image size."""
    size_samples: int = 1
    """Random subsets per size and meta-image (paper: 5)."""
    anchored_photos: int = 0
    """Keep the keypoint anchors of only this many photos per meta-image, those with the most correspondences (0: all):
    registration where few photos match the reference (night, occluders). Starts are unchanged. Use its own --output:
    records made with another value would be reused."""
    twin_anchors: Optional[Path] = None
    """Anchors from one spot (bench/twins.py): write twin copies of the benchmark here (each meta-image with a zoomed
    twin of its best-matching photo, from the same camera centre; reused when present) and register those, with the
    keypoint anchors of each twin and its photo only. Use its own --output."""
    seed: int = 0
    threads: Optional[int] = None
    """CPU threads of torch and numba (default: the cores this process may use)."""
    verbose: bool = False
    """Show COLMAP's INFO log while initialising (default: its warnings and errors only)."""


def run(args: BenchArgs, console: Console) -> Path:
    """Train, register and tabulate (module docstring), under the lock of the results directory (`atomic.output_lock`)."""
    presets = [Path(name) for name in (args.config, *args.compare_config) if name not in PRESETS]
    check_apart_from_inputs(args.output, [*args.benchmarks, args.twin_anchors, *presets])
    if args.twin_anchors is not None:
        if len(args.benchmarks) != 1:
            raise BenchmarkLayoutError(f"--twin-anchors copies one benchmark directory, and {len(args.benchmarks)} were given; expected one.")
        check_apart_from_inputs(args.twin_anchors, [*args.benchmarks, args.output, *presets])
    with output_lock(args.output):
        return benchmarked(args, console)


def benchmarked(args: BenchArgs, console: Console) -> Path:
    """`run` under the lock."""
    started = time.perf_counter()
    set_threads(args.threads)
    set_colmap_verbosity(args.verbose)
    runner = SceneRunner
    if args.twin_anchors is not None:  # the twin copies stand in for the benchmark
        build_twins(args.benchmarks[0], args.twin_anchors, console=console)
        runner = TwinSceneRunner
    scenes = read_benchmarks(args.benchmarks) if args.twin_anchors is None else read_benchmark(args.twin_anchors)
    options = BenchOptions(
        settings=load_preset(args.config), train_steps=args.train_steps, initialisers=args.initialisers,
        ablations=args.ablations, noise_levels=args.noise_levels, sizes=args.sizes, size_samples=args.size_samples, seed=args.seed,
        noise_samples=args.noise_samples, alternatives={Path(name).stem: load_preset(name) for name in args.compare_config},
        preset=Path(args.config).stem, anchored_photos=args.anchored_photos,
    )
    check_output_path(args.output)
    args.output.mkdir(parents=True, exist_ok=True)
    train_seconds = {}
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        scene_task = progress.add_task("Scenes", total=len(scenes))
        for scene in scenes:
            step_task = progress.add_task(f"{scene.name}: reference", total=args.train_steps)
            config, train_seconds[scene.name] = train_reference(scene, args.output, args.train_steps, lambda s: progress.update(step_task, completed=s + 1))
            progress.update(step_task, completed=args.train_steps)
            scene_runner = runner(scene, config, options, args.output)
            for meta in scene.metas:
                loaded = load_meta_image(meta.directory)
                for spec in scene_runner.pending(meta, len(loaded.photos)):
                    progress.reset(step_task, total=total_steps(options.alternatives.get(spec.mode, options.settings)), description=f"{scene.name}/{meta.name}: {spec.name}")
                    record = scene_runner.run(meta, loaded, spec, lambda s, total: progress.update(step_task, completed=s + 1, total=total))
                    console.print(describe(record))
            progress.remove_task(step_task)
            progress.advance(scene_task)
    records = read_records(args.output)
    compute = sum(train_seconds.values()) + sum(r["init_time_s"] + r["refine_time_s"] for r in records)
    header = [
        f"Benchmark {' + '.join(map(str, args.benchmarks))} ({len(scenes)} scenes, {sum(len(s.metas) for s in scenes)} meta-images), preset {args.config}, "
        f"references trained {args.train_steps} steps on CPU with the offline teacher.",
        f"Wall time of this invocation: {time.perf_counter() - started:.0f} s; total compute over all invocations "
        f"(training + initialisation + registration): {compute:.0f} s.",
    ]
    gap = benchmark_gap(scenes)
    if gap["measured"]:  # gap scenes: how hard their photos are to match to the reference, beside the paper's pairs
        header.append("Scenes' " + gap_sentence(gap))
    path = write_results(args.output, records, args.initialisers, header, Path(args.config).stem)
    console.print(f"Results: {path} and {args.output / 'results.csv'}")
    return path


def describe(record: dict) -> str:
    where = f"{record['scene']}/{record['meta']} {record['run']}"
    if record["before"] is None:
        return f"{where}: initialisation failed ({record['init_failure']})"
    before = f"ΔR {record['before']['dR']:.2f}° ΔT {record['before']['dT']:.3f}"
    if record["after"] is None:
        return f"{where}: {before} -> registration error ({record['refine_failure']})"
    return f"{where}: {before} -> ΔR {record['after']['dR']:.2f}° ΔT {record['after']['dT']:.3f} ({record['refine_time_s']:.0f} s)"


@dataclass
class TeacherBenchArgs:
    """How well each teacher's maps single out a photo's true pose against a render of the reference (bench/teacher.py),
    on a folder of photo/render pairs; writes teacher-benchmark.json, teacher-benchmark.md and landscapes.png."""

    pairs: Annotated[Path, tyro.conf.Positional]
    """Folder of <landmark>/photos/<name>.jpg and <landmark>/renders/<name>.jpg, each render made at its photo's pose
    with its camera (bench/pairs.py)."""
    output: Path
    """Directory to create for the results."""
    teachers: tuple[BenchTeacher, ...] = ("colour", "offline", "dense-sift", "hog-layout")
    """Teachers to measure: colour is the photometric baseline (mean colour per cell, standardised per image); add dinov2
    with --dinov2-weights."""
    dinov2_weights: Optional[Path] = None
    """Local DINOv2 ViT-S/14 weights (as TeacherConfig.weights); needed for the dinov2 teacher."""
    dinov2_input_size: int = 448
    """DINOv2's long side in pixels (448: 32 patches, the grid the other teachers have)."""
    overwrite: bool = False
    """Replace --output when it exists."""
    threads: Optional[int] = None
    """CPU threads of torch (default: the cores this process may use)."""


def run_teacher(args: TeacherBenchArgs, console: Console) -> Path:
    """Measure every teacher on every pair and write the report, the output appearing whole or not at all."""
    started = time.perf_counter()
    check_new_output_directory(args.output, args.overwrite, [args.pairs, args.dinov2_weights])
    if args.pairs.resolve() in args.output.resolve().parents:
        raise OutputPathError(f"Output directory {args.output} is inside the pairs folder {args.pairs}; expected it apart (the pairs are read, never written).")
    set_threads(args.threads)
    pairs = read_pairs(args.pairs)
    describers = build_describers(args.teachers, args.dinov2_weights, args.dinov2_input_size)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        task = progress.add_task("Pairs", total=len(pairs))
        records, shown = run_pairs(pairs, describers, lambda i: progress.update(task, completed=i + 1))
    summary = summarise(records)
    header = (f"Teacher benchmark on {args.pairs} ({len(pairs)} pairs, {len(summary['sift']) - 1} landmarks); "
              f"wall time {time.perf_counter() - started:.0f} s on {torch.get_num_threads()} threads.")
    with atomic_directory(args.output, overwrite=args.overwrite) as staging:
        tables = write_report(staging, records, summary, header)
        landscape_figure(staging / "landscapes.png", shown)
    console.print(header)
    for table in tables:
        console.print(table)
    console.print(f"Results: {args.output / 'teacher-benchmark.md'}, teacher-benchmark.json and landscapes.png")
    return args.output


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["teacher"]:
        teacher_args = cli.parse(TeacherBenchArgs, args=argv[1:], prog="sg-bench teacher")

        def teacher_body() -> int:
            run_teacher(teacher_args, Console())
            return 0

        return cli_main(teacher_body)
    args = cli.parse(BenchArgs, args=argv, prog="sg-bench")

    def body() -> int:
        run(args, Console())
        return 0

    return cli_main(body)


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
