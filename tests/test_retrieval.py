"""initialisers/retrieval.py on hand-made inputs: which reference image a photo is matched against (bag of visual
words) and which reference pairs are matched (exhaustive, co-visible, nearest centres)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sg_nerfstudio.initialisers.features import ImageFeatures
from sg_nerfstudio.initialisers.retrieval import VisualWordIndex, reference_pairs


def features_from(prototypes: np.ndarray, count: int, rng: np.random.Generator) -> ImageFeatures:
    """`count` SIFT-like descriptors scattered around the given [P, 128] prototypes."""
    chosen = prototypes[rng.integers(0, len(prototypes), count)]
    descriptors = np.clip(chosen + rng.normal(0.0, 6.0, chosen.shape), 0, 255).astype(np.uint8)
    return ImageFeatures(keypoints=np.zeros((count, 4), np.float32), descriptors=descriptors)


def test_a_photo_retrieves_the_reference_image_that_shares_its_words():
    rng = np.random.default_rng(0)
    prototypes = rng.integers(0, 256, (5, 8, 128)).astype(np.float64)  # 8 words of its own for each of 5 images
    reference = [features_from(prototypes[i], 120, rng) for i in range(5)]
    index = VisualWordIndex(reference, words=40, seed=0)
    for i in range(5):
        photo = features_from(prototypes[i], 60, rng)  # other descriptors of the same words
        assert index.most_similar(photo, 2)[0] == i
    mixed = ImageFeatures(np.zeros((80, 4), np.float32), np.concatenate([
        features_from(prototypes[3], 50, rng).descriptors, features_from(prototypes[1], 30, rng).descriptors,
    ]))
    assert index.most_similar(mixed, 2) == [3, 1]  # ranked by the words shared
    empty = ImageFeatures(np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8))
    assert index.most_similar(empty, 3) == [0, 1, 2]  # no words: every score 0, the stable order
    again = VisualWordIndex(reference, words=40, seed=0)
    np.testing.assert_array_equal(again.centroids, index.centroids)  # seeded: the same vocabulary each run


def observation(image_id: int) -> SimpleNamespace:
    return SimpleNamespace(image_id=image_id)


def point(*image_ids: int) -> SimpleNamespace:
    return SimpleNamespace(track=SimpleNamespace(elements=[observation(i) for i in image_ids]))


def reconstruction(points: list, centres: dict[int, tuple[float, float, float]]) -> SimpleNamespace:
    """The parts of a pycolmap.Reconstruction that reference_pairs reads."""
    images = {i: SimpleNamespace(projection_center=lambda c=c: np.asarray(c, np.float64)) for i, c in centres.items()}
    return SimpleNamespace(points3D=dict(enumerate(points)), images=images, num_points3D=lambda: len(points))


def test_small_reference_sets_are_paired_exhaustively():
    model = reconstruction([point(3, 7)], {})
    assert reference_pairs(model, [3, 7, 9], exhaustive_limit=3, neighbours=1) == [(3, 7), (3, 9), (7, 9)]


def test_large_reference_sets_pair_each_image_with_those_sharing_most_points():
    points = [point(3, 7)] * 5 + [point(3, 12)] * 4 + [point(7, 9)] * 3 + [point(9, 12)] + [point(9, 99)] * 9  # 99: not a reference image
    model = reconstruction(points, {})
    # each image's best partner: 3-7 (5 shared), 7-3, 9-7 (3; 99 does not count), 12-3 (4)
    assert reference_pairs(model, [3, 7, 9, 12], exhaustive_limit=2, neighbours=1) == [(3, 7), (3, 12), (7, 9)]
    # two or three each: 3-7, 3-12, 7-3, 7-9, 9-7, 9-12, 12-3, 12-9; none without a shared point (3-9, 7-12)
    for neighbours in (2, 3):
        assert reference_pairs(model, [3, 7, 9, 12], exhaustive_limit=2, neighbours=neighbours) == [(3, 7), (3, 12), (7, 9), (9, 12)]


def test_a_model_without_points_pairs_nearest_camera_centres():
    model = reconstruction([], {3: (0, 0, 0), 7: (1, 0, 0), 9: (3, 0, 0), 12: (10, 0, 0)})
    assert reference_pairs(model, [3, 7, 9, 12], exhaustive_limit=2, neighbours=1) == [(3, 7), (7, 9), (9, 12)]
    assert reference_pairs(model, [3, 7, 9, 12], exhaustive_limit=2, neighbours=2) == [(3, 7), (3, 9), (7, 9), (7, 12), (9, 12)]
