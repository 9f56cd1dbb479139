"""Registered meta-images' cameras inside nerfstudio's viewer: frustums, toggles and the clicked-camera panel.

One camera frustum per photo and pose kind of every registration (`inputs.Registration`):

    initial       red     the transform registration started from
    final         green   the registered transform
    ground_truth  blue    only with --gt

Scene nodes are named `/registrations/<meta-image>/<kind>/<photo>`; the GUI gets one folder per meta-image
with a checkbox for the whole meta-image and one per kind. Clicking a frustum moves that browser's viewer
camera to the frustum (as nerfstudio does for training cameras) and shows, in the "Selected camera" folder,
the photo (undistorted, left) beside the reference model rendered from that pose (right).

Frames: a registration maps meta-image coordinates to the reference world; `dataparser_transforms.json`
maps the reference world to nerfstudio's dataparser frame. Each photo's COLMAP camera is moved by the
composition once (`Sim3.move_camera`, OpenCV axes throughout); the viewer's scene is the dataparser frame
times `VISER_NERFSTUDIO_SCALE_RATIO`, and only nerfstudio's `Cameras` get OpenGL axes.
"""

from __future__ import annotations

import base64
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.frames import camera_to_world, opengl_camera_to_world
from sg_nerfstudio.geometry.meta_image import Photo
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.viewer.inputs import Registration

Array = np.ndarray
KIND_COLOURS: dict[str, tuple[int, int, int]] = {
    "initial": (255, 40, 40),
    "final": (40, 220, 40),
    "ground_truth": (40, 110, 255),
}
KIND_LABELS = {"initial": "initial (red)", "final": "final (green)", "ground_truth": "ground truth (blue)"}
PANEL_LONG_SIDE = 320
"""Long side in pixels of the photo and of the render shown side by side for a clicked frustum."""
THUMBNAIL_LONG_SIDE = 64
"""Long side of the photo drawn on each frustum's image plane."""


@dataclass
class Frustum:
    """A drawn camera: which photo, under which transform, and its pose in the dataparser frame.

    Attributes:
        name: its scene node, /registrations/<meta>/<kind>/<photo>.
        cam_from_dataparser: [3, 4] OpenCV world-to-camera in the dataparser frame.
        handle: the viser `CameraFrustumHandle` of that node.
    """

    name: str
    registration: Registration
    photo: Photo
    kind: str
    cam_from_dataparser: Array
    handle: object


# ----------------------------------------------------------------------------------------------- frames


def viewer_pose(cam_from_dataparser: Array) -> tuple[Array, Array]:
    """(wxyz [4], position [3]) in the viewer's scene of an OpenCV world-to-camera [3, 4] in the dataparser frame.

    viser's cameras use OpenCV axes, so the orientation is the camera-to-world rotation itself (nerfstudio's
    `Viewer.init_scene` reaches the same from its OpenGL poses by a half turn about x); positions are
    scaled by the viewer's scale ratio."""
    import viser.transforms as vtf
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    pose = camera_to_world(cam_from_dataparser)
    return vtf.SO3.from_matrix(pose[:, :3]).wxyz, pose[:, 3] * VISER_NERFSTUDIO_SCALE_RATIO


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


def render_rgb(model, cam_from_dataparser: Array, K: Array, width: int, height: int) -> Array:
    """[H, W, 3] uint8: the model's rgb output for one pinhole camera (OpenCV world-to-camera, dataparser frame)."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    camera = Cameras(
        camera_to_worlds=torch.from_numpy(opengl_camera_to_world(cam_from_dataparser)).float()[None],
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        width=width, height=height, camera_type=CameraType.PERSPECTIVE,
    ).to(model.device)
    with torch.no_grad():
        rgb = model.get_outputs_for_camera(camera)["rgb"]
    return (rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def photo_and_render(model, frustum: Frustum) -> Array:
    """[h, 2w + 4, 3] uint8: the undistorted photo (left) beside the model rendered from the frustum's pose."""
    image, K = frustum.photo.load_resized(PANEL_LONG_SIDE)
    height, width = image.shape[:2]
    render = render_rgb(model, frustum.cam_from_dataparser, K, width, height)
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

    def __init__(self, viewer, registrations: list[Registration], world_to_dataparser: Sim3, frustum_scale: float):
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

    def _add_registration(self, registration: Registration, world_to_dataparser: Sim3, frustum_scale: float) -> None:
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
            self.thumbnails[key] = photo.load_resized(THUMBNAIL_LONG_SIDE)[0]
        return self.thumbnails[key]

    def _add_frustums(self, registration: Registration, kind: str, meta_to_dataparser: Sim3, frustum_scale: float) -> None:
        for photo in registration.meta.photos:
            cam_from_dataparser = meta_to_dataparser.move_camera(photo.cam_from_world)
            wxyz, position = viewer_pose(cam_from_dataparser)
            fov, aspect = vertical_fov_and_aspect(photo)
            name = frustum_name(registration.name, kind, photo.name)
            handle = self.server.scene.add_camera_frustum(
                name=name, fov=fov, aspect=aspect, scale=frustum_scale, color=KIND_COLOURS[kind], wxyz=wxyz, position=position,
                image=self._thumbnail(photo),
            )
            frustum = Frustum(name, registration, photo, kind, cam_from_dataparser, handle)
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
        try:
            with self.render_lock:
                panel = photo_and_render(self.viewer.get_model(), frustum)
        except InputError as error:  # e.g. the photo became unreadable: say so in the panel, keep the viewer alive
            self.selection.content = f"**{frustum.registration.name} / {frustum.photo.name}**: {error}"
            return
        title = f"**{frustum.registration.name} / {frustum.photo.name}**, {KIND_LABELS[frustum.kind]} pose  \nphoto (left), reference model from this pose (right)"
        self.selection.content = title + "\n\n" + markdown_image(panel, f"{frustum.photo.name} and render")


