"""nerfstudio's own viewer on the reference model, with registered meta-images' cameras drawn (`scene.py`).

`start_viewer` checks the inputs, loads the model exactly as `ns-viewer` does (output types rgb / depth /
accumulation / features / feature_pca, training cameras, render and export tabs), starts
`nerfstudio.viewer.viewer.Viewer` without what means nothing for a frozen model (training controls, step
counter, the title bar's online logo) and adds the registration scene; `ViewerSession.stop()` frees the port
and its threads.

Resolution: nerfstudio's render state machine renders at a reduced resolution while the camera moves (sized
from the measured rendering speed for 30 fps) and at "Max res" when it stops. The default `--max-res 256`
keeps the CPU rasterizer responsive; raise it (or the "Max res" slider) for sharper still frames.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import torch
import tyro
from rich.console import Console

from sg_nerfstudio.splat.trained import load_pipeline, open_trained_run
from sg_nerfstudio.viewer.inputs import read_registrations
from sg_nerfstudio.viewer.scene import RegistrationScene


@dataclass
class ViewRegistrationArgs:
    """Open nerfstudio's viewer on a trained sg-feature-splat with registered meta-images' cameras drawn."""

    load_config: Path
    """config.yml of the trained sg-feature-splat reference model."""
    registration: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction]
    """A result directory <output-dir>/<meta-image>/ of ns-register-meta (holding transform.json), or an
    <output-dir> holding several; repeat the flag for more."""
    gt: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    """Ground-truth transform (gt_transform.json, meta -> reference world) per meta-image, in the order the
    meta-images are listed at start-up (registration flags in order, an <output-dir>'s entries by name)."""
    meta_image: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    """Meta-image directories (photos + COLMAP model) per meta-image in the same order, when they are no
    longer where transform.json's "meta_image" says."""
    port: int = 7007
    """Port of the viewer's web page and websocket (viser moves to the next free one if it is taken)."""
    host: str = "127.0.0.1"
    """Address the viewer listens on (0.0.0.0 to reach it from other machines)."""
    max_res: int = 256
    """Initial "Max res" of the viewer: resolution of still frames; frames while moving are smaller."""
    frustum_scale: float = 0.15
    """Size of the registration frustums in viewer units (nerfstudio draws training cameras at 0.1)."""



@dataclass
class ViewerSession:
    """A running nerfstudio Viewer with registration frustums; `stop()` frees the port and its threads."""

    viewer: object
    scene: RegistrationScene
    pipeline: object
    stopped: bool = field(default=False)

    @property
    def port(self) -> int:
        return self.viewer.viser_server.get_port()

    @property
    def url(self) -> str:
        return f"http://{self.viewer.config.websocket_host}:{self.port}"

    def stop(self, timeout: float = 10.0) -> None:
        """Stop rendering threads and the viser server (idempotent)."""
        if self.stopped:
            return
        self.stopped = True
        machines = list(self.viewer.render_statemachines.values())
        for machine in machines:
            machine.running = False
        stop_viser_server(self.viewer.viser_server, timeout)
        for machine in machines:
            machine.join(timeout)


def stop_viser_server(server, timeout: float) -> None:
    """Close viser's websocket server on its own event loop, stop that loop and join its worker threads.

    viser 0.2.7's `ViserServer.stop()` closes the websocket server from the calling thread without waking its
    event loop, so the port stays bound and the server thread keeps running; this does the same through the
    loop, then stops it (its thread ends) and shuts down the executor that runs GUI / scene callbacks.
    """
    websock = server._websock_server
    loop = websock._broadcast_buffer.event_loop
    ws_server = websock._ws_server

    async def close() -> None:
        ws_server.close()
        await ws_server.wait_closed()
        for task in asyncio.all_tasks():
            if task is not asyncio.current_task():
                task.cancel()

    asyncio.run_coroutine_threadsafe(close(), loop).result(timeout)
    loop.call_soon_threadsafe(loop.stop)
    websock._thread_executor.shutdown(wait=True, cancel_futures=True)
    if server._share_tunnel is not None:
        server._share_tunnel.close()


def start_viewer(args: ViewRegistrationArgs, console: Console) -> ViewerSession:
    """Validate the inputs, load the model as ns-viewer does, start nerfstudio's Viewer and draw the cameras."""
    from nerfstudio.utils import eval_utils  # noqa: F401  first: importing writer first is circular in nerfstudio
    from nerfstudio.utils import writer
    from nerfstudio.viewer.viewer import Viewer

    run = open_trained_run(args.load_config)
    registrations = read_registrations(args.registration, args.meta_image, args.gt, args.load_config, console)
    pipeline, _, step = load_pipeline(run, "cuda" if torch.cuda.is_available() else "cpu", "test")
    config = run.config
    config.viewer.websocket_port = args.port
    config.viewer.websocket_host = args.host
    viewer = Viewer(
        config.viewer, log_filename=run.config_path.parent / config.viewer.relative_log_filename,
        datapath=pipeline.datamanager.get_datapath(), pipeline=pipeline, share=False, train_lock=threading.Lock(),
    )
    config.logging.local_writer.enable = False  # as ns-viewer: no log lines, but the viewer's speed statistics
    writer.setup_local_writer(config.logging, max_iter=config.max_num_iterations, banner_messages=viewer.viewer_info)
    viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="completed", eval_dataset=pipeline.datamanager.eval_dataset)
    viewer.control_panel._max_res.value = args.max_res
    show_only_what_a_registration_needs(viewer)
    scene = RegistrationScene(viewer, registrations, run.world_to_dataparser, args.frustum_scale)
    viewer.update_scene(step=step)
    return ViewerSession(viewer, scene, pipeline)


def show_only_what_a_registration_needs(viewer) -> None:
    """Hide nerfstudio's training controls (Pause / Resume Training, Train Speed, Train Util, the "Step"
    counter: the model is frozen) and its title bar, whose logo and links are fetched from the internet."""
    for button in (viewer.pause_train, viewer.resume_train, viewer.stats_markdown):
        button.visible = False
    for element in (viewer.control_panel._train_speed, viewer.control_panel._train_util):
        element.set_hidden(True)
    viewer.viser_server.gui.configure_theme(titlebar_content=None, control_layout="collapsible", dark_mode=True, brand_color=(255, 211, 105))
