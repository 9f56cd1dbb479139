"""`sg-demo`: the whole pipeline on the built-in synthetic scene, on CPU, in a few minutes.

    sg-demo [--output sg_demo] [--train-steps 3000] [--config fast-cpu] [--scene default|tiny]

1. generate the built-in synthetic landmark (reference capture + front and rear meta-images);
2. train a small sg-feature-splat reference on CPU with the weight-free offline teacher;
3. register each meta-image with ns-register-meta's session from its ground truth perturbed by 5°, 0.1
   scene units and 10% scale in random directions (the benchmarks' start);
4. print the before/after table and where the reports are.

Everything it reads ships inside the package (scene presets, registration presets), so it runs from any
directory and from a non-editable install.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sg_nerfstudio import cli
from sg_nerfstudio.atomic import check_output_path
from sg_nerfstudio.errors import InputError, cli_main
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
from sg_nerfstudio.registration.session import RegistrationJob, run_job
from sg_nerfstudio.registration.settings import load_preset
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.splat.training import cpu_config, save, short_cpu_schedule, train
from sg_nerfstudio.synthetic import PRESETS, generate_scene


@dataclass
class DemoArgs:
    output: Path = Path("sg_demo")
    """Everything goes here: scene/, reference/ (trained model), registrations/."""
    train_steps: int = 3000
    """CPU training steps of the reference model."""
    config: str = "fast-cpu"
    """Registration preset: a name (paper, fast-cpu, fast-cpu-features) or a YAML file."""
    scene: Literal["default", "tiny"] = "default"
    """Built-in scene preset: `default` (the demo), `tiny` (48x36 photos, one meta-image: a smoke test)."""
    perturbation_deg: float = 5.0
    perturbation_translation: float = 0.1
    perturbation_scale: float = 0.1
    seed: int = 0
    threads: Optional[int] = None
    """CPU threads of torch and numba (default: the cores this process may use)."""


def train_reference(scene: Path, output: Path, steps: int, console: Console) -> Path:
    """A small CPU sg-feature-splat of the reference capture; returns its config.yml."""
    teacher = TeacherConfig(name="offline", input_size=256)
    config = short_cpu_schedule(cpu_config(scene / "reference", output, steps, teacher, experiment_name="reference"))
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console) as progress:
        task = progress.add_task("Training the reference model (CPU)", total=steps)
        trainer = train(config, lambda *_: progress.advance(task))
    return save(trainer, config)


def perturbed_initialisations(scene: Path, output: Path, args: DemoArgs) -> tuple[list[Path], list[Path], list[Path]]:
    """Per meta-image: its directory, a perturbed initial transform file and its ground truth file."""
    rng = np.random.default_rng(args.seed)
    metas, inits, gts = [], [], []
    for meta_dir in sorted((scene / "meta").iterdir()):
        gt_path = meta_dir / "gt_transform.json"
        truth = Sim3.read_json(gt_path, "Ground truth")
        meta = load_meta_image(meta_dir)
        start = perturbed(truth, meta.centres, rng, args.perturbation_deg, args.perturbation_translation, args.perturbation_scale)
        init_path = output / f"init_{meta_dir.name}.json"
        init_path.write_text(json.dumps({"matrix": np.asarray(start).tolist()}, indent=2))
        metas.append(meta_dir)
        inits.append(init_path)
        gts.append(gt_path)
    return metas, inits, gts


def run(args: DemoArgs, console: Console) -> int:
    started = time.perf_counter()
    set_threads(args.threads)
    settings = load_preset(args.config)
    check_output_path(args.output)
    if args.output.exists() and any(args.output.iterdir()):
        raise InputError(f"Demo output {args.output} exists and is not empty; choose another --output or remove it.")
    args.output.mkdir(parents=True, exist_ok=True)
    scene = args.output / "scene"
    console.rule("1/3 synthetic scene")
    generate_scene(PRESETS[args.scene], scene)
    console.print(f"Scene in {scene} ({time.perf_counter() - started:.0f} s)")
    console.rule("2/3 reference model")
    config_path = train_reference(scene, args.output, args.train_steps, console)
    console.print(f"Reference model: {config_path} ({time.perf_counter() - started:.0f} s)")
    console.rule("3/3 registration")
    metas, inits, gts = perturbed_initialisations(scene, args.output, args)
    job = RegistrationJob(
        load_config=config_path, meta_image=tuple(metas), output_dir=args.output / "registrations",
        config=args.config, init=tuple(str(p) for p in inits), gt=tuple(gts), settings=settings, device="cpu", threads=args.threads,
    )
    run_job(job, console)
    console.print(f"Demo finished in {time.perf_counter() - started:.0f} s. Reports: {args.output / 'registrations'}/<meta-image>/report/")
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    args = cli.parse(DemoArgs, args=list(sys.argv[1:] if argv is None else argv), prog="sg-demo")
    return cli_main(lambda: run(args, Console()))


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
