"""The dense initialiser (no SIFT): its geometry, its consensus, and `auto` falling back to it on a gap scene."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.initialisers import Initialiser, InitialiserSettings, ReferenceSource
from sg_nerfstudio.initialisers.dense import (
    DenseInitError, DenseInitSettings, Placement, ReferenceMaps, ReferenceView, camera_hypothesis, consensus_similarity,
)
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.synthetic import PRESETS, generate_scene
from sg_nerfstudio.synthetic.capture import look_at, pinhole_camera
from sg_nerfstudio.synthetic.appearance import EARTH_LOOK

SMALL = replace(
    PRESETS["tiny"], reference_size=(96, 72), photo_size=(96, 72), n_ring=16, n_aerial=4, meta_images=("front:5",),
    occluder_rate=0.0, appearance_strength=0.5, n_sparse_points=1500,
)
"""Small enough to build in seconds, large enough (96 px) for 16-cell teacher maps."""


def pose(eye, target) -> np.ndarray:
    return look_at(np.asarray(eye, float), np.asarray(target, float)).matrix()


class _Views:
    """A stand-in for ReferenceMaps with one view (camera_hypothesis reads `.views` only)."""

    def __init__(self, view: ReferenceView):
        self.views = [view]


def test_a_placement_at_the_centre_at_the_view_s_scale_proposes_the_view_itself():
    camera = pinhole_camera(1, 160, 120, 60.0)
    view = ReferenceView("v.png", camera, pose([0, -10, 2], [0, 0, 2]), depth=10.0)
    centre = np.array([camera.principal_point_x, camera.principal_point_y])
    same = camera_hypothesis(Placement(0, 1.0, 20.0, centre), _Views(view), photo_focal_cells=20.0)
    np.testing.assert_allclose(same, view.cam_from_world, atol=1e-9)


def test_a_placement_turns_towards_where_the_photo_centre_landed_and_moves_by_the_scale():
    camera = pinhole_camera(1, 160, 120, 60.0)
    focal = camera.focal_length_x
    view = ReferenceView("v.png", camera, pose([0, -10, 2], [0, 0, 2]), depth=10.0)
    right = np.array([camera.principal_point_x + focal * np.tan(np.radians(5.0)), camera.principal_point_y])
    turned = camera_hypothesis(Placement(0, 1.0, 20.0, right), _Views(view), photo_focal_cells=20.0)
    assert rotation_angle_deg(turned[:, :3] @ view.cam_from_world[:, :3].T) == pytest.approx(5.0, abs=1e-6)
    centre = np.array([camera.principal_point_x, camera.principal_point_y])
    closer = camera_hypothesis(Placement(0, 1.0, 40.0, centre), _Views(view), photo_focal_cells=20.0)  # scene twice as large
    np.testing.assert_allclose(-closer[:, :3].T @ closer[:, 3], [0.0, -5.0, 2.0], atol=1e-9)


def test_the_consensus_finds_the_similarity_most_photos_agree_with_among_decoys():
    rng = np.random.default_rng(0)
    truth = Sim3.from_parts(1.7, Rotation.random(random_state=0).as_matrix(), rng.normal(size=3))
    cam_from_meta = np.stack([pose(rng.normal(0, 2, 3) + [0, -8, 0], [0, 0, 0]) for _ in range(5)])
    moved = np.stack([truth.move_camera(p) for p in cam_from_meta])
    hypotheses = [(i, moved[i], 0.5) for i in range(4)]  # photo 4 has only decoys
    hypotheses += [(i, pose(rng.normal(0, 5, 3), rng.normal(0, 1, 3)), 0.9) for i in range(5) for _ in range(2)]
    transform, agreeing = consensus_similarity(cam_from_meta, hypotheses, max_rotation_deg=5.0, max_centre_error=0.2)
    assert agreeing == [0, 1, 2, 3]
    errors = pose_errors(list(cam_from_meta), transform, truth)
    assert errors.rotation_deg < 1e-6 and errors.translation < 1e-6


def test_no_two_photos_agreeing_is_no_start():
    cam_from_meta = np.stack([pose([0, -8, 0], [0, 0, 0]), pose([3, -8, 0], [0, 0, 0])])
    assert consensus_similarity(cam_from_meta, [(0, cam_from_meta[0], 1.0)], 5.0, 0.2) is None


@pytest.fixture(scope="module")
def gap_scene(tmp_path_factory) -> Path:
    """A small gap scene (EARTH_LOOK reference): SIFT gives no start there."""
    output = tmp_path_factory.mktemp("dense") / "gap"
    generate_scene(replace(SMALL, reference_look=EARTH_LOOK), output)
    return output


def test_auto_falls_back_to_the_dense_start_where_sift_gives_none(gap_scene, tmp_path):
    source = ReferenceSource(gap_scene / "reference" / "colmap" / "sparse" / "0", gap_scene / "reference" / "images")
    initialiser = Initialiser(source, InitialiserSettings(cache_dir=tmp_path / "cache"))
    meta = load_meta_image(gap_scene / "meta" / "front")
    sift = initialiser(meta, "colmap")
    result = initialiser(meta, "auto")
    truth = Sim3.from_matrix(json.loads((gap_scene / "meta" / "front" / "gt_transform.json").read_text())["matrix"])
    assert not sift.succeeded
    assert result.method == "dense" and result.note.startswith("auto: the dense start, as SIFT gave none (Initialisation 'colmap' failed")
    errors = pose_errors([p.cam_from_world for p in meta.photos], result.transform, truth)
    assert errors.rotation_deg < 15.0 and errors.translation < 0.3, errors
    assert len(result.agreeing_photos) >= 3
    again = Initialiser(source, InitialiserSettings(cache_dir=tmp_path / "cache"))(meta, "dense")
    np.testing.assert_array_equal(again.transform.matrix, result.transform.matrix)  # no random draw anywhere


def test_a_reference_without_observed_points_is_refused_in_one_sentence(tmp_path):
    model = pycolmap.Reconstruction()
    camera = pinhole_camera(1, 96, 72, 60.0)
    model.add_camera_with_trivial_rig(camera)
    for index, eye in enumerate(([0, -10, 2], [5, -10, 2]), start=1):
        image = pycolmap.Image(name=f"v{index}.png", camera_id=1, image_id=index)
        model.add_image_with_trivial_frame(image, look_at(np.array(eye, float), np.zeros(3)))
    with pytest.raises(DenseInitError, match=r"observe the reference's 3D points \(for their depth\); 0 of the model's 2 images do\.$"):
        ReferenceMaps(model, tmp_path, DenseInitSettings())


class _DenseOnly:
    """A stand-in Initialiser whose dense start is given (or fails, or raises); it counts its calls."""

    def __init__(self, outcome):
        self.outcome, self.calls, self.progress = outcome, 0, None

    def __call__(self, meta, method):
        assert method == "dense"
        self.calls += 1
        if isinstance(self.outcome, Exception):
            raise self.outcome
        return self.outcome


def test_the_dense_start_goes_beside_the_given_one_only_where_asked_unanchored_and_different(tmp_path):
    """ns-register-meta's choice of the starts beside the given one (`session.dense_start_beside`), with a stand-in
    initialiser: one line for a start added and for a dense start that failed, nothing otherwise."""
    from rich.console import Console

    from sg_nerfstudio.errors import InputError
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
    from sg_nerfstudio.initialisers.pipeline import InitResult
    from sg_nerfstudio.registration.session import dense_start_beside
    from sg_nerfstudio.registration.settings import load_preset

    meta = type("Meta", (), {"name": "front"})()
    given, other = Sim3.identity(), Sim3.from_parts(1.5, np.eye(3), np.array([1.0, 0.0, 0.0]))
    found = lambda transform: InitResult("dense", "front", transform, None, [], ["a", "b", "c"], 0.0, note="dense: 3 of 5 photos agree")
    failed = InitResult("dense", "front", None, "the placements of its 5 photos ... give no Sim(3)", [], [], 0.0)
    fast = load_preset("fast-cpu")
    assert fast.hypotheses.dense_start
    anchors = [PhotoKeypoints("a", np.zeros((1, 2)), np.zeros((1, 3)))]
    console = Console(record=True, width=200, file=open(tmp_path / "console.txt", "w"))
    cases = [
        (fast, [], _DenseOnly(found(other)), [("dense", other)], "front: the dense start (dense: 3 of 5 photos agree) is optimised beside"),
        (fast.changed(hypotheses={"dense_start": False}), [], _DenseOnly(found(other)), [], None),
        (fast, anchors, _DenseOnly(found(other)), [], None),  # keypoint anchors hold the pose
        (fast, [], _DenseOnly(found(given)), [], None),  # --init dense: nothing beside it
        (fast, [], _DenseOnly(failed), [], "front: no dense start beside the given one: the placements"),
        (fast, [], _DenseOnly(InputError("The reference images cannot be read.")), [], "front: no dense start beside the given one: The reference images"),
    ]
    for settings, keypoints, initialiser, expected, line in cases:
        assert dense_start_beside(initialiser, meta, given, settings, keypoints, console) == expected
        said = " ".join(console.export_text(clear=True).split())
        assert (line in said) if line else said == ""
        assert initialiser.calls == (0 if (keypoints or not settings.hypotheses.dense_start) else 1)
    assert dense_start_beside(None, meta, given, fast, [], console) == []
