"""`sg-view-registration`: nerfstudio's viewer on the reference model, with registered meta-images' cameras.

    sg-view-registration --load-config outputs/reference/sg-feature-splat/<time>/config.yml \\
        --registration registrations/front [--registration registrations/rear | --registration registrations] \\
        [--gt scenes/church/meta/front/gt_transform.json ...] [--port 7007] [--host 127.0.0.1] [--max-res 256]

Initial poses in red, registered in green, ground truth in blue (sg_nerfstudio/viewer/). Ctrl+C stops it.
"""

from __future__ import annotations

import sys
import time
from typing import Optional

from rich.console import Console

from sg_nerfstudio import cli
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.viewer.session import ViewRegistrationArgs, start_viewer


def serve(args: ViewRegistrationArgs, console: Console) -> int:
    """Start the viewer and keep it up until Ctrl+C."""
    session = None
    try:
        session = start_viewer(args, console)
        console.print(f"Viewer at {session.url} (Ctrl+C to stop)", soft_wrap=True)
        while True:
            time.sleep(0.1)
    except KeyboardInterrupt:  # the way to leave; during start-up there is nothing to stop yet
        if session is not None:
            session.stop()
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    args = cli.parse(ViewRegistrationArgs, args=list(sys.argv[1:] if argv is None else argv), prog="sg-view-registration")
    return cli_main(lambda: serve(args, Console()))


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
