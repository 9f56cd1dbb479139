"""Initial transforms meta-image -> reference world from SIFT + pycolmap (paper supplement, "Initialization").

    colmap       every photo is registered on its own into the reference (SIFT matches against the
                 reference images, 2D-3D through the reference's triangulated SIFT points, absolute pose
                 with the reference fixed), then the Sim(3) comes from the registered photos' camera
                 centres with RANSAC (COLMAP's model_aligner idea; the paper uses max error 3 in the
                 metres of its GPS-scaled references); below 5 registered photos or with centres near
                 one line, from their poses instead (estimate.similarity_from_poses). With fewer than 2
                 registered photos that agree (one photo, or photos taken from one spot), the start is
                 one photo's pose and the scale of its depths (`one_photo_start`), else a failure.
    generalized  the photos' 2D-3D correspondences are pooled and the meta-image is solved as one
                 generalized camera (estimate.generalized_similarity): our analogue of gDLS+++.
    dense        no SIFT: each photo placed among the reference images by its teacher map, one Sim(3) that
                 most photos agree with (dense.py); for references SIFT cannot match (renders of a coarse model)
    auto         colmap, then generalized, then dense: the first that gives a start (its note says which)

A failure is a result with `failure` set to one sentence and no transform, never an exception; bad
inputs (missing reference model or images) raise InputError subclasses.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Literal, Optional

import numpy as np
import pycolmap
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sg_nerfstudio.initialisers.estimate import (
    AbsolutePoseSettings,
    GeneralizedPose,
    GeneralizedSettings,
    Observations,
    PhotoKeypoints,
    PhotoPose,
    centre_of,
    centres_degenerate,
    generalized_similarity,
    register_photo,
    similarity_from_centres,
    similarity_from_one_photo,
    similarity_from_poses,
)
from sg_nerfstudio.initialisers.dense import DenseInitSettings, DenseStart, ReferenceMaps, dense_start, mean_focal
from sg_nerfstudio.initialisers.features import ImageFeatures, MatchSettings, SiftExtractor, SiftSettings, VerifiedMatcher, default_cache_dir
from sg_nerfstudio.initialisers.reference_cloud import (
    PairingSettings,
    Progress as ProgressFactory,
    ReferenceCloud,
    ReferenceSource,
    ReferenceSourceError,
    build_reference_cloud,
)
from sg_nerfstudio.initialisers.retrieval import VisualWordIndex
from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.splat.trained import read_trainer_config

Array = np.ndarray
Method = Literal["colmap", "generalized", "dense", "auto"]
METHODS: tuple[str, ...] = ("colmap", "generalized", "dense", "auto")


RIG_ANCHOR_MIN_INLIERS = 6
"""Fewest inliers under the generalized pose for a photo that does not register alone to lend its keypoints as anchors
(`Initialiser.keypoints`): six 2D-3D correspondences determine a pose, and the registration's camera fit holds the photo
by its SfM prior besides."""
CENTRE_RANSAC_MIN_PHOTOS = 5
"""Below this many registered photos the centre RANSAC (3-point samples) cannot reject an outlier and is poorly
conditioned; the pose-based similarity is used instead (`estimate.similarity_from_poses`)."""


@dataclass
class InitialiserSettings:
    """Settings of the SIFT + pycolmap initialisers (COLMAP's defaults where COLMAP has one)."""

    alignment_max_error: Optional[float] = None
    """RANSAC inlier distance of the camera-centre Sim(3), reference world units. Default: 5% of the median
    distance of the reference cameras to their centroid (the reference's scale is arbitrary; the paper's 3
    was metres of GPS-scaled references)."""
    one_photo_start: bool = True
    """When exactly one photo registers (colmap), or several do but give no Sim(3) that two of them fit (colmap: photos
    taken from one spot, whose centres give no scale; the one with the most inliers), or the generalized pose finds no
    rig of two photos and exactly one photo registers on its own (generalized): start from that photo's pose with the
    scale of its depths
    (`estimate.similarity_from_one_photo`; the registration then searches the scale with the dense objective) rather
    than failing. False: such a meta-image fails to initialise, as a classical pipeline would."""
    min_registered_photos: int = 2
    """colmap: fewest photos that must register and agree with the Sim(3). Two suffice for the pose-based similarity
    (rotation from their orientations, scale and translation from their two centres, agreement checked on both) and
    are what a 3-photo meta-image with one photo too weak to register offers; the centre RANSAC needs 3 of its own."""
    retrieval_count: int = 30
    """Reference images a photo is matched against when the reference has more than `exhaustive_limit`."""
    cache_dir: Optional[Path] = None
    """Where SIFT features and the reference's SIFT triangulation are cached
    (default: $XDG_CACHE_HOME/sg_nerfstudio/initialisers)."""
    sift: SiftSettings = field(default_factory=SiftSettings)
    matching: MatchSettings = field(default_factory=MatchSettings)
    pairing: PairingSettings = field(default_factory=PairingSettings)
    absolute_pose: AbsolutePoseSettings = field(default_factory=AbsolutePoseSettings)
    generalized: GeneralizedSettings = field(default_factory=GeneralizedSettings)
    dense: DenseInitSettings = field(default_factory=DenseInitSettings)

    def resolved_cache_dir(self) -> Path:
        return Path(self.cache_dir) if self.cache_dir is not None else default_cache_dir()


@dataclass
class InitResult:
    """Outcome of one initialiser on one meta-image.

    Attributes:
        transform: meta -> reference world, None on failure.
        failure: one sentence when the initialiser could not produce a transform.
        photos: per photo, its own registration (colmap) or inlier count (generalized).
        agreeing_photos: photos whose registered centre fits the Sim(3) (colmap) or that contribute
            inliers to the generalized pose.
    """

    method: str
    meta_name: str
    transform: Optional[Sim3]
    failure: Optional[str]
    photos: list[PhotoPose]
    agreeing_photos: list[str]
    wall_time_s: float
    note: Optional[str] = None
    """What the user should know of a transform that was found (e.g. the colmap start of a single registered photo)."""

    @property
    def succeeded(self) -> bool:
        return self.transform is not None

    def as_record(self) -> dict:
        return {
            "method": self.method,
            "meta_image": self.meta_name,
            "succeeded": self.succeeded,
            "failure": self.failure,
            "wall_time_s": round(self.wall_time_s, 3),
            "agreeing_photos": self.agreeing_photos,
            "note": self.note,
            "photos": [
                {"name": p.name, "registered": p.registered, "inliers": p.num_inliers, "correspondences": p.num_correspondences}
                for p in self.photos
            ],
        }


def reference_source_from_config(config_path: Path) -> ReferenceSource:
    """The COLMAP model and images a trained sg-feature-splat was trained on (its dataparser's paths)."""
    config = read_trainer_config(config_path)
    datamanager = config.pipeline.datamanager
    parser = datamanager.dataparser
    data = datamanager.data or getattr(parser, "data", None)
    if data is None or not hasattr(parser, "colmap_path") or not hasattr(parser, "images_path"):
        raise ReferenceSourceError(
            f"Config {config_path} does not use nerfstudio's COLMAP dataparser; pass --reference-colmap and --reference-images."
        )
    data = Path(data)
    colmap_path = Path(parser.colmap_path)
    images_path = Path(parser.images_path)
    return ReferenceSource(colmap_path if colmap_path.is_absolute() else data / colmap_path,
                           images_path if images_path.is_absolute() else data / images_path)


def resolve_reference_source(config_path: Optional[Path], colmap_path: Optional[Path], images_path: Optional[Path]) -> ReferenceSource:
    """Explicit paths win; a missing one is taken from the trained config's dataparser."""
    if colmap_path is not None and images_path is not None:
        return ReferenceSource(Path(colmap_path), Path(images_path))
    if config_path is None:
        raise ReferenceSourceError("The reference is unknown; pass --load-config, or both --reference-colmap and --reference-images.")
    from_config = reference_source_from_config(config_path)
    return ReferenceSource(Path(colmap_path) if colmap_path else from_config.colmap_path,
                           Path(images_path) if images_path else from_config.images_path)


def reference_keypoints(load_config: Path, meta: MetaImage) -> list[PhotoKeypoints]:
    """The meta-image's keypoint anchors from the SIFT initialiser of a trained run's own reference (its COLMAP
    model and images, from the config's dataparser), as `ns-register-meta` builds them; COLMAP's log at warnings.
    For benchmarks that register one meta-image as the command does."""
    set_colmap_verbosity(False)
    return Initialiser(resolve_reference_source(load_config, None, None), InitialiserSettings()).keypoints(meta)


def set_colmap_verbosity(verbose: bool) -> None:
    """COLMAP's own log (glog, on stderr): its INFO lines with `verbose`, else only warnings and errors
    (extraction, matching and triangulation otherwise print hundreds of lines between the progress bars)."""
    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.INFO if verbose else pycolmap.logging.Level.WARNING)


def silent_progress(description: str, total: int):
    """A progress factory that draws nothing."""
    return lambda: None


class Initialiser:
    """Builds the reference's SIFT cloud once, then initialises any number of meta-images.

    `progress` (description, total) -> advance() reports each stage; replace it between calls to draw
    into another display."""

    def __init__(self, source: ReferenceSource, settings: InitialiserSettings, progress: ProgressFactory = silent_progress):
        self.source = source
        self.settings = settings
        self.progress = progress
        self.extractor = SiftExtractor(settings.sift, settings.resolved_cache_dir())
        self.matcher = VerifiedMatcher(settings.matching)
        self._cloud: Optional[ReferenceCloud] = None
        self._cloud_error: Optional[InputError] = None
        self._index: Optional[VisualWordIndex] = None
        self._observations: dict[tuple, list[Observations]] = {}
        self._generalized_poses: dict[tuple, Optional[GeneralizedPose]] = {}
        self._reference_maps: Optional[ReferenceMaps] = None
        self._dense_starts: dict[tuple, DenseStart] = {}

    @property
    def cloud(self) -> ReferenceCloud:
        """The reference's SIFT cloud, built once; a reference it cannot be built from raises the same InputError
        again for every later meta-image without redoing the matching."""
        if self._cloud_error is not None:
            raise self._cloud_error
        if self._cloud is None:
            try:
                self._cloud = build_reference_cloud(
                    self.source, self.extractor, self.settings.matching, self.settings.pairing, self.settings.resolved_cache_dir(), self.progress
                )
            except InputError as error:
                self._cloud_error = error
                raise
        return self._cloud

    def check_reference(self) -> None:
        """Fail fast (InputError) on a missing or unreadable reference model or image folder."""
        self.source.load()

    def __call__(self, meta: MetaImage, method: Method) -> InitResult:
        if method not in METHODS:
            raise ValueError(f"unknown initialiser {method!r}")
        pycolmap.set_random_seed(self.settings.matching.seed)
        start = time.perf_counter()
        if method == "auto":
            result = self._auto(meta)
        elif method == "dense":
            result = self._dense(meta)
        elif method == "colmap":
            result = self._colmap(meta, self.observations(meta))
        else:
            result = self._generalized(meta, self.observations(meta))
        result.wall_time_s = time.perf_counter() - start
        return result

    def _auto(self, meta: MetaImage) -> InitResult:
        """colmap, generalized, dense: the first start found, with a note naming it and why the others gave none. A
        reference whose SIFT cloud cannot be built (too few points: a reference of renders) goes to dense directly."""
        reasons = []
        try:
            observations = self.observations(meta)
        except InputError as error:  # e.g. reference renders with too few SIFT matches among them for a cloud
            reasons.append(f"SIFT: {str(error).rstrip('.')}")  # a reference that cannot be read fails in dense below
            observations = None
        if observations is not None:
            for method, run in (("colmap", self._colmap), ("generalized", self._generalized)):
                result = run(meta, observations)
                if result.succeeded:
                    result.note = "; ".join(filter(None, [f"auto: the {method} start" + (f" ({'; '.join(reasons)})" if reasons else ""), result.note]))
                    return result
                reasons.append(result.failure.rstrip("."))
        result = self._dense(meta)
        result.note = "; ".join(filter(None, [f"auto: the dense start, as SIFT gave none ({'; '.join(reasons)})" if result.succeeded else None, result.note]))
        if not result.succeeded:
            result.failure = f"Initialisation 'auto' failed for meta-image '{meta.name}': {'; '.join(reasons + [result.failure.rstrip('.')])}."
        return result

    def reference_maps(self) -> ReferenceMaps:
        """The reference images' teacher maps for the dense initialiser, built once."""
        if self._reference_maps is None:
            advance = self.progress("Teacher maps of the reference images", 1)
            self._reference_maps = ReferenceMaps(self.source.load(), self.source.images_path, self.settings.dense)
            advance()
        return self._reference_maps

    def _dense(self, meta: MetaImage) -> InitResult:
        reference = self.reference_maps()
        key = tuple((str(photo.path), photo.cam_from_world.tobytes(), mean_focal(photo.camera)) for photo in meta.photos)
        if key not in self._dense_starts:  # once per set of photos: `auto` and the registration's dense start beside another share it
            advance = self.progress(f"Placing photos of {meta.name} among the reference images", 1)
            self._dense_starts[key] = dense_start(meta, reference)
            advance()
        start = self._dense_starts[key]
        photos = [PhotoPose(photo.name, None, 0, 0) for photo in meta.photos]
        if start.transform is None:
            return self._failure("dense", meta, photos, start.failure)
        note = f"dense: {len(start.agreeing_photos)} of {len(meta.photos)} photos agree ({reference.settings.teacher} maps)"
        return InitResult("dense", meta.name, start.transform, None, photos, start.agreeing_photos, 0.0, note=note)

    def keypoints(self, meta: MetaImage) -> list[PhotoKeypoints]:
        """Per photo that registers to the reference on its own (`register_photo`), its RANSAC-inlier 2D-3D
        correspondences: the anchors of `AnchorSettings.weight` (registration/anchored_start/anchors.py). A photo
        too weak to register alone (few or blurred matches, a night photo, occluders) is verified with the others
        instead: its inliers under the meta-image's generalized pose (`generalized_similarity`, the photos as one
        rig), at least RIG_ANCHOR_MIN_INLIERS of them. Photos verified neither way are left out. Raises InputError
        when the reference cannot be used."""
        observations = self.observations(meta)
        anchors, alone = [], set()
        for photo_observations in observations:
            pose = register_photo(photo_observations, self.settings.absolute_pose)
            if pose.registered:
                mask = pose.inlier_mask
                anchors.append(PhotoKeypoints(photo_observations.name, photo_observations.points2D[mask], photo_observations.points3D[mask]))
                alone.add(photo_observations.name)
        if len(alone) < len(observations):
            rig = self.generalized_pose(meta, observations)
            for name, (points2D, points3D) in (rig.inliers if rig is not None else {}).items():
                if name not in alone and len(points2D) >= RIG_ANCHOR_MIN_INLIERS:
                    anchors.append(PhotoKeypoints(name, points2D, points3D))
        return anchors

    def generalized_pose(self, meta: MetaImage, observations: list[Observations]) -> Optional[GeneralizedPose]:
        """The meta-image's generalized pose (`generalized_similarity`), computed once per set of photos."""
        key = tuple(str(photo.path) for photo in meta.photos)
        if key not in self._generalized_poses:
            depths = np.concatenate([p.point_depths for p in meta.photos]) if meta.photos else np.zeros(0)
            depths = depths[depths > 0]
            meta_depth = float(np.median(depths)) if len(depths) else float(np.median(np.linalg.norm(meta.centres - meta.centres.mean(0), axis=1)) + 1e-9)
            self._generalized_poses[key] = generalized_similarity(observations, meta_depth, self.settings.generalized)
        return self._generalized_poses[key]

    def observations(self, meta: MetaImage) -> list[Observations]:
        """Per photo, its 2D-3D correspondences with the reference's SIFT points (computed once per set of photos)."""
        key = tuple(str(photo.path) for photo in meta.photos)
        if key not in self._observations:
            self._observations[key] = self._match(meta)
        return self._observations[key]

    def _match(self, meta: MetaImage) -> list[Observations]:
        cloud = self.cloud
        advance = self.progress(f"SIFT on photos of {meta.name}", len(meta.photos))
        features = []
        for photo in meta.photos:
            features.append(self.extractor(photo.path))
            advance()
        advance = self.progress(f"Matching photos of {meta.name} against the reference", len(meta.photos))
        result = []
        for photo, photo_features in zip(meta.photos, features):
            points2D, points3D = self._correspondences(photo_features, photo.camera, cloud)
            result.append(Observations(photo.name, photo.camera, photo.cam_from_world, points2D, points3D))
            advance()
        return result

    def _candidates(self, features: ImageFeatures, cloud: ReferenceCloud) -> list[int]:
        if len(cloud.image_ids) <= self.settings.pairing.exhaustive_limit:
            return cloud.image_ids
        if self._index is None:
            self._index = VisualWordIndex([cloud.features[i] for i in cloud.image_ids], seed=self.settings.matching.seed)
        return [cloud.image_ids[i] for i in self._index.most_similar(features, self.settings.retrieval_count)]

    def _correspondences(self, features: ImageFeatures, camera: pycolmap.Camera, cloud: ReferenceCloud) -> tuple[Array, Array]:
        """[M, 2] photo pixels and [M, 3] reference points: unique (keypoint, 3D point) pairs over all
        verified matches with the candidate reference images."""
        pairs = set()
        for image_id in self._candidates(features, cloud):
            if not (cloud.point_ids[image_id] >= 0).any():
                continue
            matches = self.matcher.match(features, camera, cloud.features[image_id], cloud.camera(image_id))
            point_ids = cloud.point_ids[image_id][matches[:, 1]] if len(matches) else np.zeros(0, dtype=np.int64)
            pairs.update((int(k), int(p)) for k, p in zip(matches[:, 0], point_ids) if p >= 0)
        if not pairs:
            return np.zeros((0, 2)), np.zeros((0, 3))
        keypoints, point_ids = map(np.array, zip(*sorted(pairs)))
        return features.points2D[keypoints], cloud.xyz(point_ids)

    def alignment_max_error(self) -> float:
        if self.settings.alignment_max_error is not None:
            return float(self.settings.alignment_max_error)
        reconstruction = self.cloud.reconstruction
        centres = np.stack([reconstruction.images[i].projection_center() for i in self.cloud.image_ids])
        return 0.05 * float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))

    def _colmap(self, meta: MetaImage, observations: list[Observations]) -> InitResult:
        advance = self.progress(f"Registering photos of {meta.name}", len(observations))
        poses = []
        for photo_observations in observations:
            poses.append(register_photo(photo_observations, self.settings.absolute_pose))
            advance()
        registered = [(o, p) for o, p in zip(observations, poses) if p.registered]
        needed = self.settings.min_registered_photos
        if len(registered) == 1 and self.settings.one_photo_start:
            return self._one_photo(meta, poses, *registered[0])
        if len(registered) < needed:
            return self._failure("colmap", meta, poses, f"only {len(registered)} of {len(poses)} photos registered to the reference (at least {needed} are needed)")
        meta_centres = np.stack([centre_of(o.cam_from_meta) for o, _ in registered])
        reference_centres = np.stack([centre_of(p.cam_from_reference) for _, p in registered])
        max_error = self.alignment_max_error()
        found = None
        if len(registered) >= CENTRE_RANSAC_MIN_PHOTOS and not centres_degenerate(meta_centres):
            found = similarity_from_centres(meta_centres, reference_centres, max_error, self.settings.matching.seed)
        if found is None or found[1].sum() < needed:
            # Few photos, or centres near one line (a walk along a facade): their orientations fix the rotation.
            found = similarity_from_poses(
                np.stack([o.cam_from_meta for o, _ in registered]), np.stack([p.cam_from_reference for _, p in registered]), max_error,
            )
        if found is None or found[1].sum() < needed:
            agreeing = 0 if found is None else int(found[1].sum())
            reason = f"the {len(registered)} registered photos give no Sim(3) that at least {needed} of them fit within {max_error:.3g} reference units (best: {agreeing})"
            if self.settings.one_photo_start:  # e.g. photos taken from one spot: their centres give no scale
                return self._one_photo(meta, poses, *max(registered, key=lambda pair: pair[1].num_inliers), because=reason)
            return self._failure("colmap", meta, poses, reason)
        transform, inliers = found
        agreeing = [p.name for (_, p), keep in zip(registered, inliers) if keep]
        return InitResult("colmap", meta.name, Sim3(transform), None, poses, agreeing, 0.0)

    def _one_photo(
        self, meta: MetaImage, poses: list[PhotoPose], observations: Observations, pose: PhotoPose, method: str = "colmap",
        because: Optional[str] = None,
    ) -> InitResult:
        """The start of `method` from one registered photo (`similarity_from_one_photo`): its pose, and the scale from the
        median depths of what it sees in the meta-image and in the reference (`one_photo_start`). Used when exactly one
        photo registered, or (colmap, `because`) when the registered photos gave no Sim(3): the one with the most inliers
        (photos taken from one spot, whose centres give no scale, or that disagree)."""
        photo = next(p for p in meta.photos if p.name == observations.name)
        inliers = observations.points3D[pose.inlier_mask]
        reference_depths = (inliers @ pose.cam_from_reference[:, :3].T + pose.cam_from_reference[:, 3])[:, 2]
        transform = similarity_from_one_photo(
            observations.cam_from_meta, pose.cam_from_reference,
            photo.median_depth,
            float(np.median(reference_depths[reference_depths > 0])) if (reference_depths > 0).any() else float("nan"),
        )
        if transform is None:
            return self._failure(method, meta, poses, f"only {photo.name} of {len(poses)} photos registered to the reference, and its depths give no scale")
        note = f"one photo registered ({photo.name})" if because is None else f"{because}; starting from {photo.name} alone"
        return InitResult(method, meta.name, Sim3(transform), None, poses, [photo.name], 0.0,
                          note=f"{note}: the scale is a first guess from its depths")

    def _generalized(self, meta: MetaImage, observations: list[Observations]) -> InitResult:
        advance = self.progress(f"Generalized pose of {meta.name}", 1)
        pose = self.generalized_pose(meta, observations)
        advance()
        photos = [PhotoPose(o.name, None, 0 if pose is None else pose.inliers_per_photo.get(o.name, 0), len(o.points2D)) for o in observations]
        if pose is None and self.settings.one_photo_start:
            alone = [(o, register_photo(o, self.settings.absolute_pose)) for o in observations]
            registered = [(o, p) for o, p in alone if p.registered]
            if len(registered) == 1:  # one photo cannot form a rig: the colmap initialiser's start from it
                return self._one_photo(meta, [p for _, p in alone], *registered[0], method="generalized")
        if pose is None:
            total = sum(len(o.points2D) for o in observations)
            settings = self.settings.generalized
            return self._failure("generalized", meta, photos, f"the photos' {total} correspondences with the reference give no generalized pose with {settings.min_inliers} inliers from at least {settings.min_photos} photos")
        agreeing = [name for name, count in pose.inliers_per_photo.items() if count > 0]
        return InitResult("generalized", meta.name, pose.transform, None, photos, agreeing, 0.0)

    @staticmethod
    def _failure(method: str, meta: MetaImage, photos: list[PhotoPose], reason: str) -> InitResult:
        return InitResult(method, meta.name, None, f"Initialisation '{method}' failed for meta-image '{meta.name}': {reason}.", photos, [], 0.0)


@contextmanager
def rich_progress(console: Console) -> Iterator[ProgressFactory]:
    """A progress factory drawing one rich bar per stage."""
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True) as progress:
        def factory(description: str, total: int):
            task = progress.add_task(description, total=total)
            return lambda: progress.advance(task)

        yield factory


