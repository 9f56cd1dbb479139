"""Fast checks of the registration's render-free parts on the tiny scene's meta-image, without a trained reference:
the hypotheses around a start (registration/hypotheses.py), the anchored start's scale search, bundle adjustment and
entry (registration/anchored_start/). Keypoint anchors come from the meta-image's own sparse points (exact in the
synthetic scene) taken to the world by the ground truth; a stand-in for the photos' losses scores how far each moved
camera centre lies from where the ground truth puts it."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from sg_nerfstudio.geometry.alignment import camera_centres
from sg_nerfstudio.geometry.meta_image import load_meta_image, radial_k1_index
from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration import hypotheses
from sg_nerfstudio.registration.anchored_start import bundle_adjustment, prealigns, start_from_anchors
from sg_nerfstudio.registration.anchored_start.anchors import FIT_KERNEL_FRACTION, Anchoring
from sg_nerfstudio.registration.anchored_start.scale_search import scale_the_anchors_leave_free
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration.optimize import hypothesis_margin
from sg_nerfstudio.registration.schedules import History
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.registration.stages import Stage
from test_register import _CentreLosses, with_one_photo_turned, with_wrong_focal_lengths

UNTRIMMED = RegistrationSettings().changed(robust={"rule": "none"})
"""Every photo counts: the stand-in losses have no outliers to trim."""


@pytest.fixture(scope="module")
def front(tiny_scene):
    """(the tiny scene's front meta-image, its ground truth meta -> world)."""
    directory = tiny_scene / "meta" / "front"
    return load_meta_image(directory), Sim3.read_json(directory / "gt_transform.json", "Ground truth")


class CentreLosses(_CentreLosses):
    """test_register's stand-in for PhotoLosses, differentiable in the transform (a stage can take Adam steps on it)."""

    def __init__(self, meta, truth: Sim3):
        super().__init__(meta, truth)
        self.timings = defaultdict(float)

    def __call__(self, transform, indices):
        moved = transform.apply(torch.from_numpy(self.centres))  # a torch Sim3, as stages and objective_at pass it
        target = torch.from_numpy(self.target)
        return [((moved[i] - target[i]) ** 2).sum() for i in indices], torch.ones(len(indices))


def own_anchors(meta, truth: Sim3, per_photo: int, seed: int) -> list[PhotoKeypoints]:
    """Exact keypoint anchors without a reference: per photo, `per_photo` of the sparse points it observes, seen where
    its camera (distortion included) projects them, with their position in the world under `truth`."""
    rng = np.random.default_rng(seed)
    anchors = []
    for photo in meta.photos:
        seen = photo.points_camera[photo.points_camera[:, 2] > 0]
        seen = seen[rng.choice(len(seen), min(per_photo, len(seen)), replace=False)]
        rotation, translation = photo.cam_from_world[:, :3], photo.cam_from_world[:, 3]
        anchors.append(PhotoKeypoints(photo.name, np.asarray(photo.camera.img_from_cam(seen)), truth.apply((seen - translation) @ rotation)))
    return anchors


def about_centroid(meta, transform: Sim3, rotation_vector=(0.0, 0.0, 0.0), factor: float = 1.0) -> Sim3:
    """`transform` followed by a rotation (rotation vector, radians) and a scaling about the moved cameras' centroid."""
    moved = Sim3.from_parts(factor, Rotation.from_rotvec(rotation_vector).as_matrix(), np.zeros(3))
    return moved.about(meta.centroid_under(transform)) @ transform


def test_hypotheses_turn_the_start_by_the_angle_about_axes_spread_over_the_sphere(front):
    meta, truth = front
    start = perturbed(truth, meta.centres, np.random.default_rng(0), 5.0, 0.1, 0.1)
    turned = hypotheses.hypotheses_around(start, meta, 6, 15.0)
    axes = np.array([axis for axis, _ in turned])
    assert axes.shape == (6, 3) and np.allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-3)
    assert np.allclose(axes[:, 2], [5 / 6, 3 / 6, 1 / 6, -1 / 6, -3 / 6, -5 / 6], atol=1e-4)  # a Fibonacci sphere from pole to pole
    assert np.abs(axes @ axes.T - np.eye(6)).max() < 0.99  # no two axes alike
    for axis, transform in turned:
        assert hypotheses.rotation_between_deg(transform, start) == pytest.approx(15.0, abs=1e-6)
        relative = Rotation.from_matrix(transform.rotation @ start.rotation.T).as_rotvec()
        assert np.allclose(relative, np.radians(15.0) * np.array(axis), atol=1e-4)  # about that axis
        assert transform.scale == pytest.approx(start.scale, rel=1e-12)
        assert np.allclose(meta.centroid_under(transform), meta.centroid_under(start), atol=1e-9)  # about the cameras' centroid

    assert hypotheses.scaled_about_centroid(start, meta, 1.0) is start
    larger = hypotheses.scaled_about_centroid(start, meta, 1.25)
    assert larger.scale / start.scale == pytest.approx(1.25, rel=1e-12) and hypotheses.rotation_between_deg(larger, start) < 1e-6
    centroid = meta.centroid_under(start)
    assert np.allclose(meta.centroid_under(larger), centroid, atol=1e-9)
    spread = lambda transform: np.linalg.norm(transform.apply(meta.centres) - centroid, axis=1)
    assert np.allclose(spread(larger), 1.25 * spread(start), rtol=1e-9)


def test_rotation_between_two_similarities_ignores_their_scales_and_translations():
    turn = Rotation.from_rotvec(np.radians(30.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    a = Sim3.from_parts(2.0, turn, np.array([1.0, -2.0, 3.0]))
    b = Sim3.from_parts(0.5, np.eye(3), np.zeros(3))
    assert hypotheses.rotation_between_deg(a, b) == pytest.approx(30.0, abs=1e-9)
    assert hypotheses.rotation_between_deg(b, a) == pytest.approx(30.0, abs=1e-9)
    assert hypotheses.rotation_between_deg(a, a) == pytest.approx(0.0, abs=1e-5)


def test_the_best_hypothesis_is_the_one_the_judge_prefers_among_the_kept(front):
    """The start is the truth turned by -20 deg about the third hypothesis axis and scaled by 1.25, so the hypothesis
    (third axis, 0.8) is the truth. The stage's coarse losses prefer another hypothesis (a decoy); with every candidate
    kept the judge (losses around the truth) picks the truth; with one kept, the decoy wins unjudged."""
    meta, truth = front
    axes = [np.array(axis) for axis, _ in hypotheses.hypotheses_around(truth, meta, 6, 20.0)]
    start = about_centroid(meta, about_centroid(meta, truth, -np.radians(20.0) * axes[2]), factor=1.25)
    decoy_axis, decoy = hypotheses.hypotheses_around(start, meta, 6, 20.0)[4]
    judge = CentreLosses(meta, truth)
    stage = Stage("coarse", CentreLosses(meta, decoy), 0, 0.01, None)
    settings = UNTRIMMED.changed(hypotheses={"count": 6, "rotation_deg": 20.0, "scales": (0.8,), "kept": 14})
    history = History([photo.name for photo in meta.photos])
    winner, records, next_step = hypotheses.best_hypothesis(stage, judge, meta, start, settings, history, 7, None)
    assert next_step == 7 and len(records) == 14 and history.rows == []
    assert np.allclose(winner.matrix, truth.matrix, atol=1e-4)  # the axes are given to 4 decimals
    assert (records[0]["axis"], records[0]["scale"]) == (decoy_axis, 1.0) and records[0]["start_objective_coarse"] < 1e-12
    best = min(records, key=lambda record: record["final_objective"])
    assert (best["axis"], best["scale"]) == (axes[2].tolist(), 0.8) and best["final_objective"] < 1e-8 and best["agrees_with_winner"]
    assert not records[0]["agrees_with_winner"]  # the decoy ends 20 deg or more from the truth
    kept_one, records, _ = hypotheses.best_hypothesis(stage, judge, meta, start, settings.changed(hypotheses={"kept": 1}), history, 7, None)
    assert len(records) == 1 and np.allclose(kept_one.matrix, decoy.matrix, atol=1e-12)


def test_each_kept_hypothesis_is_optimised_and_only_the_winners_steps_are_recorded(front):
    meta, truth = front
    start = perturbed(truth, meta.centres, np.random.default_rng(3), 10.0, 0.05, 0.05)
    losses = CentreLosses(meta, truth)
    settings = UNTRIMMED.changed(hypotheses={"count": 4, "rotation_deg": 10.0, "kept": 2})
    history, steps = History([photo.name for photo in meta.photos]), []
    winner, records, next_step = hypotheses.best_hypothesis(
        Stage("coarse", losses, 5, 0.01, 0.001), losses, meta, start, settings, history, 0, lambda step, _: steps.append(step),
    )
    assert next_step == 5 and steps == [0, 1, 2, 3, 4] * 2  # both kept hypotheses optimised
    assert len(history.rows) == 5 * len(meta.photos) and {row["stage"] for row in history.rows} == {"coarse"}
    assert len(records) == 2 and min(r["final_objective"] for r in records) < min(r["start_objective_coarse"] for r in records)
    assert pose_errors(meta.poses, winner, truth).rotation_deg < pose_errors(meta.poses, start, truth).rotation_deg


def test_other_starts_are_always_optimised_and_the_judge_picks_among_every_end(front):
    """A start far off and the dense initialiser's near the truth, with no rotations around the start (fast-cpu): both
    run the stage and the near one wins; with the two swapped the given one wins; with rotations around the start of
    which one is kept, the other start still runs beside it."""
    meta, truth = front
    far = perturbed(truth, meta.centres, np.random.default_rng(4), 25.0, 0.3, 0.2)
    near = perturbed(truth, meta.centres, np.random.default_rng(5), 1.0, 0.01, 0.01)
    losses = CentreLosses(meta, truth)
    stage = Stage("main", losses, 0, 0.01, None)  # no steps: each end is its start, so the judge's choice is known
    history = History([photo.name for photo in meta.photos])
    winner, records, _ = hypotheses.best_hypothesis(stage, losses, meta, far, UNTRIMMED, history, 0, None, other_starts=[("dense", near)])
    assert np.allclose(winner.matrix, near.matrix) and [(r["start"], r["won"]) for r in records] == [("given", False), ("dense", True)]
    assert not records[0]["agrees_with_winner"] and records[1]["final_objective"] < records[0]["final_objective"]
    assert records[0]["rotation_from_winner_deg"] == pytest.approx(hypotheses.rotation_between_deg(far, near)) and records[1]["rotation_from_winner_deg"] < 1e-5
    margin, elsewhere = hypothesis_margin(records)
    assert margin == pytest.approx(records[0]["final_objective"] / records[1]["final_objective"] - 1.0) and elsewhere == records[0]["rotation_from_winner_deg"]
    assert hypothesis_margin(records[1:]) == (None, None)  # every end agrees with the winner
    winner, records, _ = hypotheses.best_hypothesis(stage, losses, meta, near, UNTRIMMED, history, 0, None, other_starts=[("dense", far)])
    assert np.allclose(winner.matrix, near.matrix) and [(r["start"], r["won"]) for r in records] == [("given", True), ("dense", False)]
    one_kept = UNTRIMMED.changed(hypotheses={"count": 4, "rotation_deg": 10.0, "kept": 1})
    winner, records, _ = hypotheses.best_hypothesis(stage, losses, meta, far, one_kept, history, 0, None, other_starts=[("dense", near)])
    assert len(records) == 2 and records[1]["start"] == "dense" and np.allclose(winner.matrix, near.matrix)


def test_the_scale_search_scales_about_the_one_anchored_camera(front):
    """One photo's anchors leave the scale about its camera free: from 30% too large there, the search finds the
    factor the other photos' stand-in losses prefer, and the anchored camera does not move. Anchors of two photos apart,
    of every photo, or none: nothing to search."""
    meta, truth = front
    anchors = own_anchors(meta, truth, 30, seed=0)
    first = meta.photos[0]
    centre = truth.apply(first.centre)
    start = Sim3.scaling_about(1.3, centre) @ truth
    anchoring = lambda keypoints: Anchoring(meta, keypoints, Sim3.identity(), 1.0)
    found, record = scale_the_anchors_leave_free(_CentreLosses(meta, truth), anchoring(anchors[:1]), meta, start, UNTRIMMED)
    assert record["photos"] == [first.name] and record["factor"] == pytest.approx(1 / 1.3, abs=0.01)
    assert record["anchor_motion_px"] < 0.1 and record["anchor_error_px"] < 0.01
    assert np.allclose(found.apply(first.centre), centre, atol=1e-9)
    assert pose_errors(meta.poses, found, truth).translation < 0.05 * pose_errors(meta.poses, start, truth).translation
    for keypoints in ([anchors[0], anchors[-1]], anchors, []):
        unchanged, none = scale_the_anchors_leave_free(_CentreLosses(meta, truth), anchoring(keypoints), meta, start, UNTRIMMED)
        assert unchanged is start and none is None


def test_bundle_adjustment_recovers_the_similarity_and_a_wrong_focal_length(front):
    """Anchors of every photo but one, seen through the true cameras; the meta-image's SfM put every focal length 5%
    long and turned the photo without anchors by 1 deg. The adjustment from a start 3 deg off maps the meta-image's
    cameras onto the true ones, the focal lengths back by 1/1.05 and the turned photo back by its own tracks."""
    meta, truth = front
    turned = meta.photos[0].name
    anchors = [k for k in own_anchors(meta, truth, 40, seed=1) if k.name != turned]
    wrong = with_wrong_focal_lengths(with_one_photo_turned(meta, 1.0), 1.05)
    assert bundle_adjustment.adjustable(wrong)
    start = perturbed(truth, meta.centres, np.random.default_rng(2), 3.0, 0.05, 0.05)
    adjusted = bundle_adjustment.adjust_with_anchors(wrong, anchors, Sim3.identity(), start, True, True, FIT_KERNEL_FRACTION)
    assert adjusted is not None
    transform, poses, focal_change, radial_k1 = adjusted
    assert sorted(poses) == sorted(photo.name for photo in meta.photos)
    assert sorted(focal_change) == sorted(radial_k1) == sorted(int(photo.camera.camera_id) for photo in meta.photos)
    assert np.allclose(list(focal_change.values()), 1 / 1.05, atol=1e-3), focal_change
    true_k1 = {int(p.camera.camera_id): float(p.camera.params[radial_k1_index(p.camera)]) for p in meta.photos}
    assert all(abs(radial_k1[c] - k1) < 1e-3 for c, k1 in true_k1.items()), (radial_k1, true_k1)
    for photo in meta.photos:  # each adjusted camera, carried by the transform, is the true one
        assert np.allclose(transform.move_camera(poses[photo.name]), truth.move_camera(photo.cam_from_world), atol=1e-4)
    angles, shifts, depths = bundle_adjustment.pose_changes(wrong, poses)
    assert angles[0] > 0.5 and angles[1:].max() < 0.5, angles  # the turn, less what the Sim(3) took of it
    assert np.allclose(depths, [photo.median_depth for photo in meta.photos]) and shifts.shape == (len(meta.photos),)


def test_the_adjustment_holds_each_anchor_as_two_observations_of_a_constant_point(front):
    import pycolmap

    meta, truth = front
    anchors = own_anchors(meta, truth, 7, seed=2)[1:] + [PhotoKeypoints("not-a-photo.png", np.zeros((3, 2)), np.zeros((3, 3)))]
    model = pycolmap.Reconstruction(meta.reconstruction)
    own_points, own_observations = model.num_points3D(), sum(point.track.length() for point in model.points3D.values())
    config = bundle_adjustment.with_anchor_observations(model, anchors)
    anchored = sum(len(k.points2D) for k in anchors[:-1])
    assert model.num_points3D() == own_points + anchored and config.num_constant_points() == anchored
    assert sum(point.track.length() for point in model.points3D.values()) == own_observations + bundle_adjustment.ANCHOR_OBSERVATIONS * anchored
    assert sorted(config.images) == sorted(model.reg_image_ids())


def test_the_anchored_start_prealigns_fits_the_cameras_and_leaves_a_fixed_scale(front):
    """start_from_anchors with anchors of all photos but one and the adjustment: the pre-alignment and camera fit bring
    a 4 deg start onto the truth with the focal lengths fitted, every photo's pose corrected by little, the main losses
    built once for the moved meta-image, and no scale search (the anchors of four photos apart fix the scale)."""
    meta, truth = front
    anchors = own_anchors(meta, truth, 40, seed=3)[1:]
    wrong = with_wrong_focal_lengths(meta, 1.05)
    start = perturbed(truth, meta.centres, np.random.default_rng(4), 4.0, 0.05, 0.05)
    settings = UNTRIMMED.changed(anchors={"weight": 1.0, "prealign_steps": 20}, camera_fit={"focal": True, "photo_poses": True, "solver": "adjustment"})
    built = []
    main_losses = lambda moved, photos: built.append((moved, photos)) or CentreLosses(moved, truth)
    anchored = start_from_anchors(wrong, None, start, settings, Sim3.identity(), anchors, 32, main_losses)
    assert anchored.prealigned and anchored.scale_search is None and len(built) == 1 and built[0] == (anchored.meta, None)
    assert anchored.given is wrong and np.allclose(list(anchored.fit.focal_scales.values()), 1 / 1.05, atol=1e-3)
    assert [photo.focal_scale for photo in anchored.meta.photos] == [anchored.fit.focal_scales[p.name] for p in meta.photos]
    errors = pose_errors(meta.poses, anchored.transform, truth)
    assert errors.rotation_deg < 0.01 and errors.translation < 1e-3, errors
    corrections = anchored.pose_corrections(world_per_meta=2.0)
    assert sorted(corrections) == sorted(photo.name for photo in meta.photos)
    assert all(c["rotation_deg"] < 0.05 and c["centre_shift"] < 0.01 for c in corrections.values()), corrections

    plain = settings.changed(anchors={"weight": 0.0})
    assert prealigns(settings, True) and not prealigns(settings, False) and not prealigns(plain, True)
    unmoved = start_from_anchors(wrong, None, start, plain, Sim3.identity(), anchors, 32, main_losses)
    assert unmoved.transform is start and not unmoved.prealigned and unmoved.meta is wrong and unmoved.pose_corrections(1.0) == {}
    assert unmoved.camera_shift.rotation_angle_deg() == 0.0 and not unmoved.anchor


def test_own_anchors_are_exact_under_the_true_cameras(front):
    """own_anchors' points lie in front of the photos' true cameras in the world and project onto their keypoints."""
    meta, truth = front
    for photo, anchor in zip(meta.photos, own_anchors(meta, truth, 10, seed=5)):
        camera = truth.move_camera(photo.cam_from_world)
        in_camera = anchor.points3D @ camera[:, :3].T + camera[:, 3]
        assert (in_camera[:, 2] > 0).all()
        assert np.allclose(photo.camera.img_from_cam(in_camera), anchor.points2D, atol=1e-6)
        assert np.allclose(camera_centres(camera[None])[0], truth.apply(photo.centre))
