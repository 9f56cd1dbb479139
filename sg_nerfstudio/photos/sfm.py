"""Structure from motion on a photo collection with pycolmap, every model kept.

Stages (each a pycolmap call on one COLMAP database):
1. `extract_features`: SIFT, one camera per photo (`CameraMode.PER_IMAGE`: Internet photos have their own
   focal length and size), `SIMPLE_RADIAL` by default (focal, principal point, k1: COLMAP's own default for
   photos of unknown cameras);
2. matching: exhaustive up to `exhaustive_limit` photos; above it, retrieval-based pairs: each photo is
   matched with its `retrieval_neighbours` most similar photos under a tf-idf bag of visual words built from
   the collection's own SIFT descriptors (`initialisers.retrieval.VisualWordIndex`; pycolmap's vocabulary-
   tree matcher needs a vocabulary file from the internet, which this tool never downloads), then
   `match_image_pairs` on that pair list; geometric verification is pycolmap's in both cases;
3. `incremental_mapping` with `multiple_models`: every disconnected model of at least `min_model_size`
   photos is kept (the meta-images), largest first.

`diagnose` says for each photo that no model holds why, from what the database shows: too few SIFT
features, no verified pair, or verified pairs that the mapper could not use. That diagnosis replaces the mapper's
own warnings and errors ("No images with matches", "Failed to create any sparse model"), which are kept out of the
terminal unless COLMAP's log is verbose (`quiet_mapper`).
"""

from __future__ import annotations

from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np
import pycolmap

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.initialisers.features import ImageFeatures
from sg_nerfstudio.initialisers.retrieval import VisualWordIndex

Stage = Callable[[str], None]
"""stage(description): called when an SfM stage starts (for progress display)."""


class ReconstructionError(InputError):
    """Photos that structure from motion cannot turn into any model."""


class SfmSettingsError(InputError):
    """An SfM setting pycolmap cannot use (an unknown camera model)."""


def check_camera_model(name: str, option: str = "--camera-model") -> None:
    """Raise SfmSettingsError unless `name` is one of pycolmap's camera models (`pycolmap.CameraModelId`)."""
    known = [model for model in pycolmap.CameraModelId.__members__ if model != "INVALID"]
    if name not in known:
        raise SfmSettingsError(f"{option} {name!r} is not a COLMAP camera model; expected one of {', '.join(known)}.")


@dataclass(frozen=True)
class SfmSettings:
    """How photos become COLMAP models (the defaults suit a few to a few hundred photos of one landmark)."""

    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model of every photo (one camera per photo). Models with more lens terms than k1 are hard to
    determine from a few photos: Strecha fountain-P11 and Sceaux Castle split into 3-photo meta-images (`sg-make-scene
    --from-photos` defaults with `--scene.meta-camera-model`) formed 4 of 4 models under SIMPLE_RADIAL, 2 of 4 under
    RADIAL and 2 of 4 under OPENCV. The two OPENCV models were broken: the similarity that best maps their cameras onto
    the true ones left a camera 7.2 deg and 1.7 deg off (0.12-0.79 deg under SIMPLE_RADIAL; docs/measurements.md
    "Camera models with more lens terms than k1")."""
    exhaustive_limit: int = 60
    """Collections up to this many photos are matched exhaustively; larger ones by retrieval."""
    retrieval_neighbours: int = 20
    """Above the limit: photos each photo is matched with (most similar by visual words)."""
    min_model_size: int = 3
    """Smallest model kept (photos); smaller ones are reported as not registered."""
    init_min_inliers: int = 50
    """Verified matches the mapper's first pair needs (COLMAP's default, 100, rejects many 3-photo meta-images of
    photos under different light; 50 still needs a well-supported two-view geometry)."""
    min_pose_inliers: int = 20
    """2D-3D inliers a further photo needs to be registered (COLMAP's default 30 leaves the third photo of many
    3-photo meta-images out: it sees only the points its two predecessors triangulated)."""
    min_features: int = 50
    """A photo with fewer SIFT features is reported as such."""
    threads: int = -1
    """pycolmap threads (-1: all cores)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_camera_model(self.camera_model)


@dataclass
class PhotoDiagnosis:
    """What SfM made of one photo."""

    name: str
    features: int
    verified_pairs: int
    best_inliers: int
    model: Optional[int] = None  # index into SfmResult.models, None when no kept model holds it

    def reason(self, settings: SfmSettings) -> str:
        """Why no model holds this photo (one phrase)."""
        if self.features < settings.min_features:
            return f"only {self.features} SIFT features (texture-less, blurred or tiny photo)"
        if self.verified_pairs == 0:
            return "no geometrically verified match with any other photo (no overlap, or too different)"
        return (
            f"verified against {self.verified_pairs} photo(s) (best {self.best_inliers} inliers), but the mapper could not "
            f"register it in a model of at least {settings.min_model_size} photos"
        )


@dataclass
class SfmResult:
    models: list[pycolmap.Reconstruction]
    photos: dict[str, PhotoDiagnosis]
    pairing: str
    settings: SfmSettings = field(default_factory=SfmSettings)

    def unregistered(self) -> list[tuple[str, str]]:
        """(photo name, reason) for every photo that no kept model holds."""
        return [(d.name, d.reason(self.settings)) for d in self.photos.values() if d.model is None]


def reconstruct(images: Path, names: list[str], work: Path, settings: SfmSettings, stage: Optional[Stage] = None) -> SfmResult:
    """Run SfM on the photos `names` of directory `images`; the database is written to `work/database.db`.

    Returns every model of at least `settings.min_model_size` photos (largest first) and a diagnosis per photo.
    """
    stage = stage or (lambda _: None)
    if len(names) < settings.min_model_size:
        raise ReconstructionError(
            f"{len(names)} photo(s) in {images}; structure from motion needs at least {settings.min_model_size} overlapping photos."
        )
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    stage(f"SIFT on {len(names)} photos")
    _extract(database, Path(images), names, settings)
    stage("matching")
    pairing = _match(database, work, settings)
    stage("incremental mapping")
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = settings.min_model_size
    options.multiple_models = True
    options.num_threads = settings.threads
    options.random_seed = settings.seed
    options.mapper.init_min_num_inliers = settings.init_min_inliers
    options.mapper.abs_pose_min_num_inliers = settings.min_pose_inliers
    with quiet_mapper():
        found = pycolmap.incremental_mapping(str(database), str(images), str(work / "models"), options=options)
    models = sorted(
        (m for m in found.values() if m.num_reg_images() >= settings.min_model_size),
        key=lambda m: (-m.num_reg_images(), min(m.images[i].name for i in m.reg_image_ids())),
    )
    return SfmResult(models, diagnose(database, models), pairing, settings)


@contextmanager
def quiet_mapper() -> Iterator[None]:
    """While mapping: COLMAP's log at FATAL only, unless it was set to INFO (`--verbose`). A photo set that forms no
    model otherwise prints glog's warning and error lines before the one sentence `diagnose` gives."""
    level = pycolmap.logging.minloglevel
    if level > int(pycolmap.logging.Level.INFO):
        pycolmap.logging.minloglevel = int(pycolmap.logging.Level.FATAL)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _extract(database: Path, images: Path, names: list[str], settings: SfmSettings) -> None:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = settings.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = settings.threads
    extraction.max_image_size = 100000  # the working images are already capped (collection.prepare_photos)
    pycolmap.extract_features(
        str(database), str(images), image_names=list(names), camera_mode=pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
    )


def _match(database: Path, work: Path, settings: SfmSettings) -> str:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = settings.threads
    matching.use_gpu = False
    with _open(database) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        if len(images) <= settings.exhaustive_limit:
            pairs = None
        else:
            pairs = retrieval_pairs([_features(db, im.image_id) for im in images], settings.retrieval_neighbours, settings.seed)
            pairs = [(images[a].name, images[b].name) for a, b in pairs]
    if pairs is None:
        pycolmap.match_exhaustive(str(database), matching_options=matching, device=pycolmap.Device.cpu)
        return "exhaustive"
    pair_file = work / "pairs.txt"
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pair_file
    pycolmap.match_image_pairs(str(database), matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    return f"retrieval ({settings.retrieval_neighbours} most similar photos each, {len(pairs)} pairs)"


def retrieval_pairs(features: list[ImageFeatures], neighbours: int, seed: int) -> list[tuple[int, int]]:
    """Index pairs (a < b): each image with its `neighbours` most similar others under visual words."""
    index = VisualWordIndex(features, seed=seed)
    pairs = set()
    for a, feats in enumerate(features):
        for b in index.most_similar(feats, neighbours + 1):
            if b != a:
                pairs.add((min(a, b), max(a, b)))
    return sorted(pairs)


def _open(path: Path) -> "closing[pycolmap.Database]":
    return closing(pycolmap.Database.open(str(path)))


def _features(db: pycolmap.Database, image_id: int) -> ImageFeatures:
    keypoints = np.asarray(db.read_keypoints(image_id), dtype=np.float32).reshape(-1, 6)[:, :4]
    descriptors = np.asarray(db.read_descriptors(image_id).data, dtype=np.uint8).reshape(-1, 128)
    return ImageFeatures(keypoints, descriptors)


def diagnose(database: Path, models: list[pycolmap.Reconstruction]) -> dict[str, PhotoDiagnosis]:
    """Per photo: SIFT features, verified pairs, best inlier count, and which kept model holds it."""
    with _open(database) as db:
        images = {im.image_id: im.name for im in db.read_all_images()}
        found = {name: PhotoDiagnosis(name, db.num_keypoints_for_image(image_id), 0, 0) for image_id, name in images.items()}
        pair_ids, geometries = db.read_two_view_geometries()
    for pair_id, geometry in zip(pair_ids, geometries):
        inliers = len(geometry.inlier_matches)
        if inliers == 0:
            continue
        for image_id in pycolmap.pair_id_to_image_pair(pair_id):
            entry = found[images[image_id]]
            entry.verified_pairs += 1
            entry.best_inliers = max(entry.best_inliers, inliers)
    for index, model in enumerate(models):
        for image_id in model.reg_image_ids():
            found[model.images[image_id].name].model = index
    return found
