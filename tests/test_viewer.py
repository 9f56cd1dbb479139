"""sg-view-registration: nerfstudio's viewer serves the reference model with the registration frustums drawn
in its scene frame, shows photo | render for a clicked frustum, shuts down cleanly, rejects bad inputs."""

from __future__ import annotations

import base64
import copy
import json
import re
import socket
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pycolmap
import pytest
import torch
import viser.transforms as vtf
import yaml
from rich.console import Console
from websockets.sync.client import connect

from sg_nerfstudio.geometry.frames import opengl_camera_to_world
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.scripts.register_meta import main as register_main
from sg_nerfstudio.scripts.view_registration import main
from sg_nerfstudio.splat.trained import read_world_to_dataparser
from sg_nerfstudio.viewer.scene import KIND_COLOURS, frustum_name, viewer_pose
from sg_nerfstudio.viewer.session import ViewRegistrationArgs, start_viewer

KINDS = ("initial", "final", "ground_truth")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def port_accepts(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def reference_config(quick_trained) -> Path:
    return quick_trained  # the viewer needs a trained run, not an accurate one: 20 steps keep these tests fast


@pytest.fixture(scope="module")
def gt_path(tiny_scene) -> Path:
    return tiny_scene / "meta" / "front" / "gt_transform.json"


@pytest.fixture(scope="module")
def registrations(reference_config, tiny_scene, gt_path, tmp_path_factory) -> Path:
    """<output-dir> of a 2-step ns-register-meta run of the front meta-image (with ground truth)."""
    out = tmp_path_factory.mktemp("viewer") / "registrations"
    code = register_main([
        "--load-config", str(reference_config), "--meta-image", str(tiny_scene / "meta" / "front"), "--output-dir", str(out),
        "--gt", str(gt_path), "--optimiser.steps", "2", "--optimiser.photos-per-step", "2",
    ])
    assert code == 0
    return out


def view_args(reference_config, registrations, gt_path) -> ViewRegistrationArgs:
    return ViewRegistrationArgs(load_config=reference_config, registration=(registrations,), gt=(gt_path,), port=free_port(), host="127.0.0.1")


@pytest.fixture(scope="module")
def session(reference_config, registrations, gt_path):
    running = start_viewer(view_args(reference_config, registrations, gt_path), Console(quiet=True))
    yield running
    running.stop()


def scene_messages(port: int, seconds: float = 3.0) -> list[dict]:
    """What a browser receives on connecting: viser's persistent scene and GUI messages (msgpack windows)."""
    messages = []
    with connect(f"ws://127.0.0.1:{port}", open_timeout=10) as websocket:
        deadline = time.time() + seconds
        while time.time() < deadline:
            try:
                messages.extend(msgspec.msgpack.decode(websocket.recv(timeout=0.5)))
            except TimeoutError:
                if messages:
                    break
    return messages


def test_page_is_served_and_scene_holds_one_frustum_per_photo_and_kind(session, tiny_scene):
    with urllib.request.urlopen(f"http://127.0.0.1:{session.port}/", timeout=10) as response:
        assert response.status == 200
        assert b"<html" in response.read().lower()
    frustums = {m["name"]: m for m in scene_messages(session.port) if m["type"] == "CameraFrustumMessage"}
    photos = load_meta_image(tiny_scene / "meta" / "front").photos
    expected = {frustum_name("front", kind, photo.name): kind for kind in KINDS for photo in photos}
    drawn = {name: m for name, m in frustums.items() if name.startswith("/registrations/")}
    assert set(drawn) == set(expected)
    for name, kind in expected.items():
        red, green, blue = KIND_COLOURS[kind]
        assert drawn[name]["color"] == (red << 16) | (green << 8) | blue, name
    assert any(name.startswith("/cameras/camera_") for name in frustums)  # nerfstudio's own training cameras
    assert set(session.scene.groups) == {"/registrations/front"} | {f"/registrations/front/{kind}" for kind in KINDS}


def test_frustums_follow_the_transform_the_viewer_applies_to_training_cameras(session, tiny_scene, reference_config):
    """Reference photos under the identity transform must land exactly on nerfstudio's training frustums."""
    world_to_dataparser = read_world_to_dataparser(reference_config)
    model = pycolmap.Reconstruction(str(tiny_scene / "reference" / "colmap" / "sparse" / "0"))
    by_name = {image.name: image for image in model.images.values()}
    filenames = session.pipeline.datamanager.train_dataparser_outputs.image_filenames
    compared = 0
    for index, handle in session.viewer.camera_handles.items():
        image = by_name[Path(filenames[index]).name]
        wxyz, position = viewer_pose(world_to_dataparser.move_camera(image.cam_from_world().matrix()))
        np.testing.assert_allclose(position, handle.position, atol=1e-4)
        np.testing.assert_allclose(vtf.SO3(wxyz).as_matrix(), vtf.SO3(np.asarray(handle.wxyz)).as_matrix(), atol=1e-5)
        compared += 1
    assert compared >= 3


def test_clicking_a_frustum_shows_the_photo_beside_the_render(session):
    name = frustum_name("front", "final", session.scene.frustums[next(iter(session.scene.frustums))].photo.name)
    frustum = session.scene.frustums[name]
    session.scene.on_click(frustum, client=None)
    content = session.scene.selection.content
    assert frustum.photo.name in content and "final" in content
    encoded = re.search(r"data:image/jpeg;base64,([A-Za-z0-9+/=]+)", content).group(1)
    panel = cv2.imdecode(np.frombuffer(base64.b64decode(encoded), np.uint8), cv2.IMREAD_COLOR)
    width = (panel.shape[1] - 4) // 2
    photo = cv2.cvtColor(frustum.photo.load_undistorted(), cv2.COLOR_RGB2BGR)
    photo = cv2.resize(photo, (width, panel.shape[0]), interpolation=cv2.INTER_AREA)
    assert np.abs(panel[:, :width].astype(float) - photo).mean() < 8.0  # left: the photo (JPEG-compressed)
    render = panel[:, width + 4 :]
    assert render.shape[1] == width and render.std() > 5.0  # right: the model, not a blank image


def test_a_browser_gets_renders_with_feature_pca_and_its_clicks_move_the_camera(session):
    """Speak viser's protocol as the browser does: send a camera, receive nerfstudio's renders (which fill the
    "Output type" menu), click a frustum, receive the camera move; the panel then shows that photo."""
    from viser import _messages

    def send(websocket, message) -> None:
        websocket.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    frustum = session.scene.frustums[frustum_name("front", "ground_truth", session.scene.frustums[next(iter(session.scene.frustums))].photo.name)]
    received = []
    with connect(f"ws://127.0.0.1:{session.port}", open_timeout=10) as websocket:
        send(websocket, _messages.ViewerCameraMessage(
            wxyz=tuple(map(float, frustum.handle.wxyz)), position=(0.0, -30.0, 10.0), fov=0.9, aspect=4 / 3,
            look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0),
        ))
        deadline = time.time() + 120
        while time.time() < deadline and not any(m["type"] == "BackgroundImageMessage" for m in received):
            try:
                received.extend(msgspec.msgpack.decode(websocket.recv(timeout=1.0)))
            except TimeoutError:
                pass
        assert any(m["type"] == "BackgroundImageMessage" for m in received), "no render reached the browser"
        assert "feature_pca" in session.viewer.control_panel._output_render.options

        send(websocket, _messages.SceneNodeClickMessage(
            name=frustum.name, instance_index=None, ray_origin=(0.0, -30.0, 10.0), ray_direction=(0.0, 0.0, -1.0), screen_pos=(0.5, 0.5),
        ))
        moved = []
        while time.time() < deadline and not moved:
            try:
                moved = [m for m in msgspec.msgpack.decode(websocket.recv(timeout=1.0)) if m["type"] == "SetCameraPositionMessage"]
            except TimeoutError:
                pass
        assert moved, "the click did not move the camera"
        np.testing.assert_allclose(moved[-1]["position"], frustum.handle.position, atol=1e-4)
        expected = f"{frustum.photo.name}**, ground truth"
        while time.time() < deadline and expected not in session.scene.selection.content:
            time.sleep(0.05)
    assert expected in session.scene.selection.content


def test_a_toggle_per_meta_image_and_kind_hides_its_frustums(session):
    toggles = session.scene.toggles["front"]
    assert set(toggles) == {"all", *KINDS}
    for key, group in (("final", "/registrations/front/final"), ("all", "/registrations/front")):
        toggles[key].value = False
        deadline = time.time() + 5
        while session.scene.groups[group].visible and time.time() < deadline:
            time.sleep(0.02)
        assert not session.scene.groups[group].visible
        toggles[key].value = True


def test_only_what_a_registration_needs_is_shown(session):
    """No training controls for a frozen model, no title bar whose logo and links need the internet."""
    viewer = session.viewer
    assert not viewer.pause_train.visible and not viewer.resume_train.visible and not viewer.stats_markdown.visible
    assert not viewer.control_panel._train_speed.gui_handle.visible and not viewer.control_panel._train_util.gui_handle.visible
    themes = [m for m in scene_messages(session.port) if m["type"] == "ThemeConfigurationMessage"]
    assert themes and themes[-1]["titlebar_content"] is None


def test_feature_pca_is_a_stable_viewer_output(session):
    """The viewer lists the keys of get_outputs_for_camera for the camera it builds from the browser's state."""
    from nerfstudio.cameras.cameras import CameraType
    from nerfstudio.viewer.utils import CameraState, get_camera

    frustum = session.scene.frustums[next(iter(session.scene.frustums))]
    c2w = torch.from_numpy(opengl_camera_to_world(frustum.cam_from_dataparser)).float()
    state = CameraState(fov=0.9, aspect=4 / 3, c2w=c2w, camera_type=CameraType.PERSPECTIVE)
    model = session.viewer.get_model()
    first = model.get_outputs_for_camera(get_camera(state, 48, 64))
    second = model.get_outputs_for_camera(get_camera(state, 48, 64))
    assert {"rgb", "depth", "features", "feature_pca"} <= set(first)
    assert first["feature_pca"].shape == (48, 64, 3)
    assert torch.equal(first["feature_pca"], second["feature_pca"])


def test_stop_frees_the_port_and_leaves_no_thread(reference_config, registrations, gt_path):
    before = set(threading.enumerate())
    args = view_args(reference_config, registrations, gt_path)
    running = start_viewer(args, Console(quiet=True))
    assert running.port == args.port and port_accepts(args.port)
    running.stop()
    deadline = time.time() + 5
    while set(threading.enumerate()) - before and time.time() < deadline:
        time.sleep(0.05)
    assert not set(threading.enumerate()) - before
    assert not port_accepts(args.port)
    with socket.socket() as again:  # the address can be bound again
        again.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        again.bind(("127.0.0.1", args.port))


@pytest.mark.parametrize("case", ["no_transform_json", "missing_registration", "not_feature_splat", "gt_count", "moved_meta_image"])
def test_bad_inputs_fail_with_one_sentence(case, reference_config, registrations, gt_path, tmp_path, capsys):
    config, registration, extra = reference_config, registrations / "front", []
    expected = {
        "no_transform_json": "has no transform.json",
        "missing_registration": f"Registration directory {tmp_path / 'gone'} does not exist; expected <output-dir>/<meta-image>/",
        "not_feature_splat": "expected an sg-feature-splat model",
        "gt_count": "--gt was given 2 times for 1 meta-images",
        "moved_meta_image": "pass --meta-image",
    }[case]
    if case == "no_transform_json":
        registration = tmp_path / "front"
        registration.mkdir()
    elif case == "missing_registration":
        registration = tmp_path / "gone"
    elif case == "not_feature_splat":
        from nerfstudio.configs.method_configs import method_configs

        config = tmp_path / "config.yml"
        config.write_text(yaml.dump(copy.deepcopy(method_configs["splatfacto"])))
    elif case == "gt_count":
        extra = ["--gt", str(gt_path), "--gt", str(gt_path)]
    elif case == "moved_meta_image":
        registration = tmp_path / "front"
        registration.mkdir()
        record = json.loads((registrations / "front" / "transform.json").read_text())
        (registration / "transform.json").write_text(json.dumps(record | {"meta_image": str(tmp_path / "gone")}))
    capsys.readouterr()
    code = main(["--load-config", str(config), "--registration", str(registration), "--port", str(free_port()), *extra])
    err = capsys.readouterr().err
    assert code == 1
    assert expected in err, err
    assert err.strip().count("\n") == 0, err
