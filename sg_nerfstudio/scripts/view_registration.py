"""`sg-view-registration`: nerfstudio's viewer on the reference model, with registered meta-images' cameras.

    sg-view-registration --load-config outputs/reference/sg-feature-splat/<time>/config.yml \\
        --registration registrations/front [--registration registrations/rear | --registration registrations] \\
        [--gt scenes/church/meta/front/gt_transform.json ...] [--port 7007] [--host 127.0.0.1] [--max-res 256]

It starts nerfstudio's own viewer (`nerfstudio.viewer.viewer.Viewer`, exactly as `ns-viewer` does: output
types rgb / depth / accumulation / features / feature_pca, training cameras, render and export tabs) and adds
one camera frustum per photo and pose kind of every registered meta-image:

    initial       red     the transform registration started from ("initial" in transform.json)
    final         green   the registered transform ("matrix" in transform.json)
    ground_truth  blue    only with --gt (ns-register-meta does not record which --gt it was given)

Scene nodes are named `/registrations/<meta-image>/<kind>/<photo>`; the GUI gets one folder per meta-image
with a checkbox for the whole meta-image and one per kind. Clicking a frustum moves that browser's viewer
camera to the frustum (as nerfstudio does for training cameras) and shows, in the "Selected camera" folder,
the photo (undistorted, left) beside the reference model rendered from that pose (right).

Frames: a registration maps meta-image coordinates to the reference world; `dataparser_transforms.json`
maps the reference world to nerfstudio's dataparser frame; the viewer's scene is the dataparser frame times
`VISER_NERFSTUDIO_SCALE_RATIO`, with camera orientations converted as `Viewer.init_scene` converts training
cameras (OpenGL camera-to-world, then a half turn about x: viser uses OpenCV camera axes).

Resolution: nerfstudio's render state machine renders at a reduced resolution while the camera moves (sized
from the measured rendering speed for 30 fps) and at "Max res" when it stops. The default `--max-res 256`
keeps the CPU rasterizer responsive; raise it (or the "Max res" slider) for sharper still frames.
"""

from __future__ import annotations

import asyncio
import base64
import json
import re
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Optional

import cv2
import numpy as np
import torch
import tyro
from rich.console import Console
from rich.text import Text

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.registration.meta_image import MetaImage, Photo, load_meta_image
from sg_nerfstudio.registration.reference import read_trainer_config
from sg_nerfstudio.registration.sim3 import decompose

Array = np.ndarray
KIND_COLOURS: dict[str, tuple[int, int, int]] = {
    "initial": (255, 40, 40),
    "final": (40, 220, 40),
    "ground_truth": (40, 110, 255),
}
KIND_LABELS = {"initial": "initial (red)", "final": "final (green)", "ground_truth": "ground truth (blue)"}
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])
PANEL_LONG_SIDE = 320
"""Long side in pixels of the photo and of the render shown side by side for a clicked frustum."""
THUMBNAIL_LONG_SIDE = 64
"""Long side of the photo drawn on each frustum's image plane."""


class RegistrationViewError(InputError):
    """An input of sg-view-registration that cannot be shown."""


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
class Registration:
    """One meta-image's ns-register-meta result, with the transforms to draw.

    Attributes:
        name: meta-image name (the result directory's name).
        directory: the result directory holding transform.json.
        meta: the meta-image (photos, COLMAP cameras in the meta frame).
        transforms: kind ("initial", "final", "ground_truth") -> [4, 4] Sim(3) meta -> reference world.
        summary: one markdown paragraph (steps, loss, ΔR / ΔT from metrics.json when present).
    """

    name: str
    directory: Path
    meta: MetaImage
    transforms: dict[str, Array]
    summary: str


@dataclass
class Frustum:
    """A drawn camera: which photo, under which transform, and its pose in the dataparser frame.

    Attributes:
        name: its scene node, /registrations/<meta>/<kind>/<photo>.
        camera_to_world: [3, 4] OpenGL camera-to-world in the dataparser frame (nerfstudio `Cameras`).
        handle: the viser `CameraFrustumHandle` of that node.
    """

    name: str
    registration: Registration
    photo: Photo
    kind: str
    camera_to_world: Array
    handle: object


# ----------------------------------------------------------------------------------------------- inputs


def find_registration_dirs(paths: tuple[Path, ...]) -> list[Path]:
    """Result directories holding transform.json: each path itself, or else its sub-directories that do."""
    found = []
    for path in paths:
        if (path / "transform.json").is_file():
            found.append(path)
            continue
        children = sorted(p for p in path.iterdir() if not p.name.startswith(".") and (p / "transform.json").is_file()) if path.is_dir() else []
        if not children:
            raise RegistrationViewError(
                f"Registration directory {path} has no transform.json (nor do its sub-directories); expected "
                "<output-dir>/<meta-image>/ as written by ns-register-meta."
            )
        found.extend(children)
    return found


def per_registration(values: tuple[Path, ...], count: int, flag: str) -> list[Optional[Path]]:
    """One value per registration (or None for all when the flag was not given)."""
    if not values:
        return [None] * count
    if len(values) != count:
        raise RegistrationViewError(f"{flag} was given {len(values)} times for {count} meta-images; expected 0 or {count}.")
    return list(values)


def read_matrix(value, source: str) -> Array:
    """[4, 4] Sim(3) from a JSON value (a 4x4 list); `source` names it in the error."""
    try:
        matrix = np.asarray(value, dtype=np.float64)
        decompose(matrix)
    except (TypeError, ValueError) as error:
        raise RegistrationViewError(f"{source} is not a 4x4 similarity transform ({error}).") from None
    return matrix


def read_json(path: Path, what: str) -> dict:
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise RegistrationViewError(f"{what} {path} does not exist.") from None
    except (OSError, ValueError) as error:
        raise RegistrationViewError(f"{what} {path} is not readable JSON ({type(error).__name__}).") from None
    if not isinstance(record, dict):
        raise RegistrationViewError(f"{what} {path} is not a JSON object with a \"matrix\".")
    return record


def read_registration(directory: Path, meta_dir: Optional[Path], gt_path: Optional[Path]) -> Registration:
    """Read transform.json (+ metrics.json), the meta-image it names (or `meta_dir`) and the ground truth."""
    transform_path = directory / "transform.json"
    record = read_json(transform_path, "Registration file")
    if "matrix" not in record or "matrix" not in (record.get("initial") or {}):
        raise RegistrationViewError(f"{transform_path} lacks \"matrix\" or \"initial\".\"matrix\"; expected a transform.json written by ns-register-meta.")
    transforms = {
        "initial": read_matrix(record["initial"]["matrix"], f"\"initial\" in {transform_path}"),
        "final": read_matrix(record["matrix"], f"\"matrix\" in {transform_path}"),
    }
    if gt_path is not None:
        transforms["ground_truth"] = read_matrix(read_json(gt_path, "Ground-truth file").get("matrix"), f"Ground truth {gt_path}")
    if meta_dir is None:
        if "meta_image" not in record:
            raise RegistrationViewError(f"{transform_path} does not record its meta-image directory; pass --meta-image.")
        meta_dir = Path(record["meta_image"])
        if not meta_dir.is_dir():
            raise RegistrationViewError(f"Meta-image directory {meta_dir} recorded in {transform_path} does not exist; pass --meta-image with its current location.")
    meta = load_meta_image(meta_dir)
    return Registration(directory.name, directory, meta, transforms, registration_summary(directory, record, len(meta.photos)))


def registration_summary(directory: Path, record: dict, photo_count: int) -> str:
    """Markdown: photos, steps, final trimmed loss, and ΔR / ΔT before -> after when metrics.json exists."""
    text = f"{photo_count} photos, {record.get('steps', '?')} steps, trimmed loss {float(record.get('final_trimmed_loss', float('nan'))):.4f}"
    metrics_path = directory / "metrics.json"
    if metrics_path.is_file():
        try:
            metrics = json.loads(metrics_path.read_text())
            before, after = metrics["before"], metrics["after"]
            text += (
                f"  \nΔR {before['delta_R_deg']:.2f}° → {after['delta_R_deg']:.2f}°, "
                f"ΔT {before['delta_T']:.3f} → {after['delta_T']:.3f} (metrics.json)"
            )
        except (OSError, ValueError, KeyError, TypeError):
            text += "  \n(metrics.json unreadable)"
    return text


def check_reference_config(config_path: Path):
    """The TrainerConfig of a trained sg-feature-splat whose dataset and checkpoint are on disk."""
    config = read_trainer_config(config_path)
    data = Path(config.pipeline.datamanager.data or config.pipeline.datamanager.dataparser.data)
    if not data.exists():
        raise RegistrationViewError(
            f"The reference dataset {data} named in {config_path} was not found (the viewer needs it to rebuild the model); "
            "run from the directory you trained in or fix `data:` in the config."
        )
    if not (config_path.parent / "dataparser_transforms.json").is_file():
        raise RegistrationViewError(f"{config_path.parent / 'dataparser_transforms.json'} is missing; it is written by ns-train next to config.yml.")
    checkpoints = config_path.parent / config.relative_model_dir
    if not checkpoints.is_dir() or not any(checkpoints.glob("step-*.ckpt")):
        raise RegistrationViewError(f"No checkpoint (step-*.ckpt) in {checkpoints}.")
    return config


def read_world_to_dataparser(config_path: Path) -> Array:
    """[4, 4] Sim(3) reference world -> dataparser frame, x_ns = s (A x + b), from dataparser_transforms.json."""
    record = json.loads((config_path.parent / "dataparser_transforms.json").read_text())
    matrix = np.eye(4)
    matrix[:3, :4] = float(record["scale"]) * np.asarray(record["transform"], dtype=np.float64)
    return matrix


# ----------------------------------------------------------------------------------------------- frames


def dataparser_camera_to_world(cam_from_meta: Array, meta_to_dataparser: Array) -> Array:
    """[3, 4] OpenGL camera-to-world in the dataparser frame, as nerfstudio's `Cameras.camera_to_worlds`.

    Args:
        cam_from_meta: [3, 4] COLMAP world-to-camera (OpenCV axes) in the meta-image frame.
        meta_to_dataparser: [4, 4] Sim(3) meta frame -> dataparser frame (x -> s R x + t).
    """
    scale, rotation, translation = decompose(meta_to_dataparser)
    camera_to_meta = cam_from_meta[:, :3].T
    centre = -camera_to_meta @ cam_from_meta[:, 3]
    camera_to_world = np.empty((3, 4))
    camera_to_world[:, :3] = rotation @ camera_to_meta @ OPENCV_TO_OPENGL
    camera_to_world[:, 3] = scale * rotation @ centre + translation
    return camera_to_world


def viewer_pose(camera_to_world: Array) -> tuple[Array, Array]:
    """(wxyz [4], position [3]) of a camera in the viewer's scene, converted as `Viewer.init_scene` converts
    training cameras: OpenGL -> OpenCV axes by a half turn about x, positions times the viewer's scale ratio."""
    import viser.transforms as vtf
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    rotation = vtf.SO3.from_matrix(camera_to_world[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)
    return rotation.wxyz, camera_to_world[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO


def vertical_fov_and_aspect(photo: Photo) -> tuple[float, float]:
    """viser's frustum shape: vertical field of view (radians) and width / height of the undistorted photo."""
    K = photo.pinhole_intrinsics()
    return float(2.0 * np.arctan(0.5 * photo.camera.height / K[1, 1])), photo.camera.width / photo.camera.height


def node_name(*parts: str) -> str:
    """A viser scene path from parts, each reduced to [A-Za-z0-9_.-] so it adds exactly one tree level."""
    return "/" + "/".join(re.sub(r"[^A-Za-z0-9_.-]", "_", part) for part in parts)


def frustum_name(meta_name: str, kind: str, photo_name: str) -> str:
    """/registrations/<meta-image>/<kind>/<photo without extension>."""
    return node_name("registrations", meta_name, kind, str(Path(photo_name).with_suffix("")))


# ----------------------------------------------------------------------------------------------- rendering


def render_rgb(model, camera_to_world: Array, K: Array, width: int, height: int) -> Array:
    """[H, W, 3] uint8: the model's rgb output for one pinhole camera (dataparser frame, OpenGL axes)."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    camera = Cameras(
        camera_to_worlds=torch.from_numpy(camera_to_world).float()[None],
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        width=width, height=height, camera_type=CameraType.PERSPECTIVE,
    ).to(model.device)
    with torch.no_grad():
        rgb = model.get_outputs_for_camera(camera)["rgb"]
    return (rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def photo_and_render(model, frustum: Frustum) -> Array:
    """[h, 2w + 4, 3] uint8: the undistorted photo (left) beside the model rendered from the frustum's pose."""
    photo = frustum.photo
    image = photo.load_undistorted()
    factor = PANEL_LONG_SIDE / max(image.shape[:2])
    width, height = max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor))
    image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    K = photo.pinhole_intrinsics()
    K[0] *= width / photo.camera.width
    K[1] *= height / photo.camera.height
    render = render_rgb(model, frustum.camera_to_world, K, width, height)
    gap = np.full((height, 4, 3), 255, np.uint8)
    return np.concatenate([image, gap, render], axis=1)


def markdown_image(image: Array, alt: str) -> str:
    """Markdown embedding an [H, W, 3] uint8 RGB image as a JPEG data URL (viser's markdown shows it)."""
    ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok, "OpenCV failed to encode a JPEG"
    return f"![{alt}](data:image/jpeg;base64,{base64.b64encode(encoded.tobytes()).decode('ascii')})"


# ----------------------------------------------------------------------------------------------- scene


class RegistrationScene:
    """Frustums, toggles and the clicked-camera panel for registered meta-images in a nerfstudio Viewer."""

    def __init__(self, viewer, registrations: list[Registration], world_to_dataparser: Array, frustum_scale: float):
        self.viewer = viewer
        self.server = viewer.viser_server
        self.frustums: dict[str, Frustum] = {}
        self.thumbnails: dict[str, Array] = {}
        self.groups: dict[str, object] = {}
        """Scene frames /registrations/<meta> and /registrations/<meta>/<kind> (viser FrameHandle) by name."""
        self.toggles: dict[str, dict[str, object]] = {}
        """meta-image -> "all" | kind -> GUI checkbox showing / hiding that group of frustums."""
        self.render_lock = viewer.train_lock or threading.Lock()
        for registration in registrations:
            self._add_registration(registration, world_to_dataparser, frustum_scale)
        with self.server.gui.add_folder("Selected camera"):
            # Images are embedded as data URLs; an image_root only keeps viser from warning that it has none.
            self.selection = self.server.gui.add_markdown(
                "Click a registration frustum to compare its photo with the model's render from that pose.",
                image_root=registrations[0].directory if registrations else None,
            )
        self.server.on_client_connect(self.frame_registrations)

    def _add_registration(self, registration: Registration, world_to_dataparser: Array, frustum_scale: float) -> None:
        root = self._add_group(node_name("registrations", registration.name))
        kind_frames = {}
        for kind, transform in registration.transforms.items():
            kind_frames[kind] = self._add_group(node_name("registrations", registration.name, kind))
            self._add_frustums(registration, kind, world_to_dataparser @ transform, frustum_scale)
        with self.server.gui.add_folder(f"Meta-image {registration.name}"):
            self.server.gui.add_markdown(registration.summary)
            toggles = {"all": self._add_toggle(f"show {registration.name}", root)}
            for kind, frame in kind_frames.items():
                toggles[kind] = self._add_toggle(KIND_LABELS[kind], frame)
        self.toggles[registration.name] = toggles

    def _add_group(self, name: str) -> object:
        self.groups[name] = self.server.scene.add_frame(name, show_axes=False)
        return self.groups[name]

    def _add_toggle(self, label: str, node) -> object:
        checkbox = self.server.gui.add_checkbox(label, initial_value=True)

        @checkbox.on_update
        def _(_event) -> None:
            node.visible = checkbox.value

        return checkbox

    def _thumbnail(self, photo) -> Array:
        """The photo on the frustum's image plane: shows which photo it is, and the plane (unlike the 1-px
        frame lines) is easy to click."""
        key = str(photo.path)
        if key not in self.thumbnails:
            image = photo.load_undistorted()
            factor = THUMBNAIL_LONG_SIDE / max(image.shape[:2])
            size = (max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor)))
            self.thumbnails[key] = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        return self.thumbnails[key]

    def _add_frustums(self, registration: Registration, kind: str, meta_to_dataparser: Array, frustum_scale: float) -> None:
        for photo in registration.meta.photos:
            camera_to_world = dataparser_camera_to_world(photo.cam_from_world, meta_to_dataparser)
            wxyz, position = viewer_pose(camera_to_world)
            fov, aspect = vertical_fov_and_aspect(photo)
            name = frustum_name(registration.name, kind, photo.name)
            handle = self.server.scene.add_camera_frustum(
                name=name, fov=fov, aspect=aspect, scale=frustum_scale, color=KIND_COLOURS[kind], wxyz=wxyz, position=position,
                image=self._thumbnail(photo),
            )
            frustum = Frustum(name, registration, photo, kind, camera_to_world, handle)
            handle.on_click(lambda event, frustum=frustum: self.on_click(frustum, event.client))
            self.frustums[name] = frustum

    def frame_registrations(self, client) -> None:
        """Start a new browser behind and above the first meta-image's final cameras, looking past them towards
        the scene centre (the dataparser origin: nerfstudio centres the reference poses there; +z up). viser's
        default camera often sits inside the model, and far beyond the reference cameras only background
        Gaussians show, so the view stays near the cameras' distance."""
        finals = [f for f in self.frustums.values() if f.kind == "final"]
        first = [np.asarray(f.handle.position) for f in finals if f.registration is finals[0].registration] if finals else []
        if not first:
            return
        centre = np.mean(first, axis=0)
        radius = float(np.linalg.norm(centre))
        with client.atomic():
            client.camera.position = 1.25 * centre + np.array([0.0, 0.0, 0.5 * radius])
            client.camera.look_at = 0.4 * centre
            client.camera.up_direction = (0.0, 0.0, 1.0)

    def on_click(self, frustum: Frustum, client) -> None:
        """Move the clicking browser's camera to the frustum, then show photo | render in the GUI."""
        if client is not None:
            fov, _ = vertical_fov_and_aspect(frustum.photo)
            with client.atomic():
                client.camera.position = frustum.handle.position
                client.camera.wxyz = frustum.handle.wxyz
                client.camera.fov = fov
        self.show(frustum)

    def show(self, frustum: Frustum) -> None:
        """Render the model at the frustum's pose (under the viewer's render lock) and put it beside the photo."""
        with self.render_lock:
            panel = photo_and_render(self.viewer.get_model(), frustum)
        title = f"**{frustum.registration.name} / {frustum.photo.name}**, {KIND_LABELS[frustum.kind]} pose  \nphoto (left), reference model from this pose (right)"
        self.selection.content = title + "\n\n" + markdown_image(panel, f"{frustum.photo.name} and render")


# ----------------------------------------------------------------------------------------------- viewer


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
    from nerfstudio.utils.eval_utils import eval_setup  # first: importing writer first is circular in nerfstudio
    from nerfstudio.utils import writer
    from nerfstudio.viewer.viewer import Viewer

    config = check_reference_config(args.load_config)
    registrations = read_registrations(args, console)
    config, pipeline, _, step = eval_setup(args.load_config, test_mode="test")
    config.viewer.websocket_port = args.port
    config.viewer.websocket_host = args.host
    viewer = Viewer(
        config.viewer, log_filename=config.get_base_dir() / config.viewer.relative_log_filename,
        datapath=pipeline.datamanager.get_datapath(), pipeline=pipeline, share=False, train_lock=threading.Lock(),
    )
    config.logging.local_writer.enable = False  # as ns-viewer: no log lines, but the viewer's speed statistics
    writer.setup_local_writer(config.logging, max_iter=config.max_num_iterations, banner_messages=viewer.viewer_info)
    viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="completed", eval_dataset=pipeline.datamanager.eval_dataset)
    viewer.control_panel._max_res.value = args.max_res
    scene = RegistrationScene(viewer, registrations, read_world_to_dataparser(args.load_config), args.frustum_scale)
    viewer.update_scene(step=step)
    return ViewerSession(viewer, scene, pipeline)


def read_registrations(args: ViewRegistrationArgs, console: Console) -> list[Registration]:
    directories = find_registration_dirs(args.registration)
    names = [d.name for d in directories]
    if len(set(names)) != len(names):
        raise RegistrationViewError(f"Registration directories must have distinct names (one meta-image each), got {names}.")
    metas = per_registration(args.meta_image, len(directories), "--meta-image")
    gts = per_registration(args.gt, len(directories), "--gt")
    registrations = [read_registration(d, m, g) for d, m, g in zip(directories, metas, gts)]
    for registration in registrations:
        recorded = json.loads((registration.directory / "transform.json").read_text()).get("reference_config")
        if recorded and Path(recorded).resolve() != args.load_config.resolve():
            console.print(f"[yellow]{registration.name} was registered against {recorded}, not {args.load_config}.[/yellow]", soft_wrap=True)
        gt_note = "with ground truth" if "ground_truth" in registration.transforms else "no ground truth (--gt)"
        console.print(f"{registration.name}: {len(registration.meta.photos)} photos from {registration.meta.directory}, {gt_note}", soft_wrap=True)
    return registrations


def main(argv: Optional[list[str]] = None) -> int:
    console = Console()
    args = tyro.cli(ViewRegistrationArgs, args=list(sys.argv[1:] if argv is None else argv), prog="sg-view-registration")
    session = None
    try:
        session = start_viewer(args, console)
        console.print(f"Viewer at {session.url} (Ctrl+C to stop)", soft_wrap=True)
        while True:
            time.sleep(0.1)
    except InputError as error:
        Console(stderr=True).print(Text(str(error), style="red"), soft_wrap=True)
        return 1
    except KeyboardInterrupt:  # the way to leave; during start-up there is nothing to stop yet
        if session is not None:
            session.stop()
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
