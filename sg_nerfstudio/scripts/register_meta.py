"""`ns-register-meta`: ground meta-images in a frozen sg-feature-splat reference model.

    ns-register-meta --load-config outputs/.../config.yml --meta-image scene/meta/front \\
        --output-dir registrations [--init identity|colmap|generalized|init.json] \\
        [--gt scene/meta/front/gt_transform.json] [--config fast-cpu] [--steps 400 ...]

`--config` names a registration preset (paper, fast-cpu, fast-cpu-features) or a YAML file of the settings;
flags override single settings. `--init` and `--gt` take one value per meta-image (a single `--init` applies
to all). The session itself (initialisers, registration, outputs, merged/) is
`sg_nerfstudio.registration.session`. Exit status 1 for a bad input and when no meta-image was registered.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional

import tyro
from rich.console import Console

from sg_nerfstudio.registration.session import RegistrationJob, run_job
from sg_nerfstudio.registration.settings import RegistrationSettings, load_preset
from sg_nerfstudio.scripts.cli import cli_main


def parse_args(argv: list[str]) -> RegistrationJob:
    """tyro's parse, with the settings' defaults taken from `--config` (wherever it appears) when given."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", default=None)
    known, _ = pre.parse_known_args(argv)
    settings = load_preset(known.config) if known.config else RegistrationSettings()
    default = RegistrationJob(load_config=tyro.MISSING, meta_image=tyro.MISSING, output_dir=tyro.MISSING, settings=settings)
    return tyro.cli(RegistrationJob, args=argv, default=default, prog="ns-register-meta", config=(tyro.conf.OmitArgPrefixes,))


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)

    def body() -> int:
        outcomes = run_job(parse_args(argv), Console())
        return 0 if any(outcome.result is not None for outcome in outcomes) else 1

    return cli_main(body)


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
