"""`ns-register-meta`: ground meta-images in a frozen sg-feature-splat reference model.

    ns-register-meta --load-config outputs/.../config.yml --meta-image scene/meta/front \\
        --output-dir registrations [--init identity|colmap|generalized|dense|auto|init.json] \\
        [--gt scene/meta/front/gt_transform.json] [--config fast-cpu] [--optimiser.steps 400 ...]

`--config` names a registration preset (paper, fast-cpu, fast-cpu-features) or a YAML file of the settings;
flags override single settings. Without it the preset follows the device (`paper` on CUDA, a CPU preset
otherwise) and the command says which. `--init` and `--gt` take one value per meta-image (a single `--init` applies
to all). The session itself (initialisers, registration, outputs, merged/) is
`sg_nerfstudio.registration.session`. Exit status 1 for a bad input and when no meta-image was registered; 2 with `--fail-on` when a verdict is that bad.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional

import tyro
from rich.console import Console

from sg_nerfstudio import cli
from sg_nerfstudio.registration.session import RegistrationJob, default_preset, fails, run_job
from sg_nerfstudio.registration.settings import RegistrationSettings, load_preset
from sg_nerfstudio.errors import cli_main


def parse_args(argv: list[str], console: Console) -> RegistrationJob:
    """tyro's parse, with the settings' defaults taken from `--config` (wherever it appears), else from the
    preset the device calls for (see `default_preset`)."""
    pre = argparse.ArgumentParser(add_help=False)
    for flag in ("--config", "--load-config", "--device"):
        pre.add_argument(flag, default=None)
    known, _ = pre.parse_known_args(argv)
    preset = known.config
    if preset is None and known.load_config is not None and not {"-h", "--help"} & set(argv):
        preset = default_preset(Path(known.load_config), known.device or "auto")
        console.print(f"Registration preset: {preset} (no --config given; chosen for this device and reference).")
    settings = load_preset(preset) if preset else RegistrationSettings()
    default = RegistrationJob(load_config=tyro.MISSING, meta_image=tyro.MISSING, output_dir=tyro.MISSING, config=preset, settings=settings)
    return cli.parse(RegistrationJob, args=argv, default=default, prog="ns-register-meta")


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)

    def body() -> int:
        console = Console()
        job = parse_args(argv, console)
        outcomes = run_job(job, console)
        if not any(outcome.result is not None for outcome in outcomes):
            return 1
        failing = fails(outcomes, job.fail_on)
        if failing:
            Console(stderr=True).print(f"--fail-on {job.fail_on}: the verdict of {', '.join(failing)} is {job.fail_on} or worse.", soft_wrap=True)
            return 2
        return 0

    return cli_main(body)


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
