"""Which reference images a photo is matched against, and which reference pairs are matched together.

Small reference sets are matched exhaustively. For large ones a photo is matched only against the
reference images most similar to it under a bag of visual words (tf-idf over SIFT descriptors, with a
vocabulary clustered from the reference descriptors themselves, so nothing is downloaded), and
reference images are paired by co-visibility in the reference COLMAP model (or, when the model has no
points, by nearest camera centres).
"""

from __future__ import annotations

import numpy as np
import pycolmap
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from sg_nerfstudio.initialisers.features import ImageFeatures

Array = np.ndarray


def _as_unit_float(descriptors: Array) -> Array:
    values = descriptors.astype(np.float32)
    return values / np.maximum(np.linalg.norm(values, axis=1, keepdims=True), 1e-6)


class VisualWordIndex:
    """tf-idf bag-of-words over the reference images' SIFT descriptors."""

    def __init__(self, reference: list[ImageFeatures], words: int = 512, sample: int = 60000, seed: int = 0):
        rng = np.random.default_rng(seed)
        pooled = np.concatenate([f.descriptors for f in reference if len(f)], axis=0)
        chosen = pooled[rng.choice(len(pooled), size=min(sample, len(pooled)), replace=False)]
        words = max(2, min(words, len(chosen) // 4))
        self.centroids, _ = kmeans2(_as_unit_float(chosen), words, iter=10, minit="++", seed=seed)
        self._tree = cKDTree(self.centroids)
        counts = np.stack([self._counts(f) for f in reference])  # [R, W]
        documents_with_word = np.count_nonzero(counts, axis=0)
        self.idf = np.log((len(reference) + 1) / (documents_with_word + 1))
        self.reference_vectors = np.stack([self._vector(c) for c in counts])  # [R, W]

    def _counts(self, features: ImageFeatures) -> Array:
        if not len(features):
            return np.zeros(len(self.centroids))
        _, assignment = self._tree.query(_as_unit_float(features.descriptors))
        return np.bincount(assignment, minlength=len(self.centroids)).astype(np.float64)

    def _vector(self, counts: Array) -> Array:
        vector = counts / max(counts.sum(), 1.0) * self.idf
        return vector / max(np.linalg.norm(vector), 1e-12)

    def most_similar(self, features: ImageFeatures, count: int) -> list[int]:
        """Indices of the `count` reference images most similar to `features`, best first."""
        scores = self.reference_vectors @ self._vector(self._counts(features))
        return [int(i) for i in np.argsort(-scores, kind="stable")[:count]]


def reference_pairs(reconstruction: pycolmap.Reconstruction, image_ids: list[int], exhaustive_limit: int, neighbours: int) -> list[tuple[int, int]]:
    """Pairs (image_id1 < image_id2) of reference images to match for triangulation."""
    if len(image_ids) <= exhaustive_limit:
        return [(a, b) for i, a in enumerate(image_ids) for b in image_ids[i + 1:]]
    if reconstruction.num_points3D() > 0:
        return _covisible_pairs(reconstruction, image_ids, neighbours)
    return _nearest_centre_pairs(reconstruction, image_ids, neighbours)


def _covisible_pairs(reconstruction: pycolmap.Reconstruction, image_ids: list[int], neighbours: int) -> list[tuple[int, int]]:
    """Each image with the `neighbours` images sharing most 3D points with it."""
    index = {image_id: i for i, image_id in enumerate(image_ids)}
    shared = np.zeros((len(image_ids), len(image_ids)), dtype=np.int64)
    for point in reconstruction.points3D.values():
        seen = sorted({index[e.image_id] for e in point.track.elements if e.image_id in index})
        for i, a in enumerate(seen):
            shared[a, seen[i + 1:]] += 1
    shared = shared + shared.T
    pairs = set()
    for a in range(len(image_ids)):
        for b in np.argsort(-shared[a], kind="stable")[:neighbours]:
            if shared[a, b] > 0 and a != b:
                pairs.add((min(image_ids[a], image_ids[b]), max(image_ids[a], image_ids[b])))
    return sorted(pairs)


def _nearest_centre_pairs(reconstruction: pycolmap.Reconstruction, image_ids: list[int], neighbours: int) -> list[tuple[int, int]]:
    centres = np.stack([reconstruction.images[i].projection_center() for i in image_ids])
    _, nearest = cKDTree(centres).query(centres, k=min(neighbours + 1, len(image_ids)))
    pairs = {(min(image_ids[a], image_ids[b]), max(image_ids[a], image_ids[b])) for a, row in enumerate(nearest) for b in row if a != b}
    return sorted(pairs)
