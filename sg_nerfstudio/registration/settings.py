"""How one meta-image is registered (`RegistrationSettings`), and the named presets shipped with the package.

Presets are YAML files in `sg_nerfstudio/registration/presets/` (installed with the package; the repository's
`configs/register/` links to them): `paper` (the paper's settings, 12000 steps), `fast-cpu` (offline-teacher
references on CPU), `fast-cpu-features` (the paper's objective on CPU) and `wide-cpu` (fast-cpu after
coarse-to-fine stages and start hypotheses, for starts 10-30° off). Every command takes one with
`--config NAME` or `--config path/to/preset.yaml`; flags override single values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Literal, Optional

import yaml

from sg_nerfstudio.errors import InputError

ObjectiveKind = Literal["features", "teacher-on-render", "photometric"]
Robust = Literal["lts", "outlier-lts", "fixed-lts", "irls", "none"]
LossKind = Literal["l1", "l2"]
PRESETS = ("paper", "fast-cpu", "fast-cpu-features", "wide-cpu")


class PresetError(InputError):
    """A registration preset that does not exist or does not hold registration settings."""


@dataclass
class RegistrationSettings:
    """How one meta-image is registered (defaults: the paper's settings)."""

    steps: int = 12000
    """Optimisation steps (paper: 12000)."""
    lr: float = 1e-3
    """Adam learning rate on delta = (omega, nu, log s) (paper: 1e-3)."""
    lr_final: Optional[float] = None
    """Exponential decay of the learning rate to this value at the last step; None keeps it constant (paper)."""
    adam_eps: float = 1e-8
    objective: ObjectiveKind = "features"
    """features: decoded feature field vs the photos' teacher maps (paper); teacher-on-render: the teacher
    applied to the rendered RGB vs the same maps; photometric: colours vs the photos."""
    loss: LossKind = "l1"
    robust: Robust = "lts"
    """lts (paper: the median rule), outlier-lts (only photos far above the others are ignored), fixed-lts,
    irls or none (see registration/robust.py)."""
    lts_percentile: float = 50.0
    """lts / fixed-lts: images with a loss above this percentile of the previous iteration's losses are
    ignored (50 = median)."""
    outlier_z: float = 3.0
    """outlier-lts: images with a loss above median + outlier_z x robust scale of the previous iteration's
    losses are ignored."""
    trim_after: float = 0.0
    """Fraction of each stage's steps in which every photo counts (the plain mean) before the robust rule
    trims: the rule then starts from a pose that has settled, where occluded photos rank above the clean ones
    (away from the answer every photo's loss sits near the same floor and the rule drops photos no worse than
    the others). 0: the rule from the first step (paper); 0 in every preset (docs/measurements.md, "The robust loss")."""
    images_per_step: int = 0
    """Photos rendered per step; 0 = all of them (paper)."""
    retrim_every: int = 1
    """Steps between re-decisions of which photos the robust rule counts: a step that re-decides renders every photo,
    the steps between render only those it counted (`schedules.RetrimSchedule`). 1: every step (paper)."""
    teacher_input_size: Optional[int] = None
    """Teacher input size for the photos; default: the one the reference model was trained with (or the render
    teacher's own default when `render_teacher` names another one)."""
    render_teacher: Optional[Literal["offline", "dense-sift"]] = None
    """teacher-on-render and photometric only: the weight-free descriptor applied to the renders and the photos
    (offline: oriented-gradient histograms; dense-sift: kornia's dense RootSIFT); default: the reference's own
    teacher. The `features` objective compares the model's distilled field, so it always uses that teacher."""
    render_scale: float = 2.0
    """Long side of the renders as a multiple of the teacher grid (the paper renders at full resolution;
    1-2 keeps CPU cost low for `features`, whose renders are resized to the grid). Never more than the
    photo's own long side, and for teacher-on-render never more than the teacher's input size."""
    near_plane: float = 0.7
    """Near plane in dataparser units against floaters (paper: 0.7); lowered automatically to half the
    nearest sparse-point depth of the meta-image so it never cuts away what the photos see."""
    pyramid: tuple[int, ...] = ()
    """Coarse-to-fine: coarse stages run before the main one, each the teacher at the main input size divided
    by a factor (e.g. 4 2: cells 4x then 2x as large, a wider basin), coarsest first. Empty: main stage only."""
    pyramid_steps: int = 60
    """Steps of each coarse stage (learning rate: lr x factor, decaying tenfold)."""
    hypotheses: int = 0
    """With a pyramid: rotations of the start by `hypothesis_deg` about this many axes (a Fibonacci sphere)
    scored at the coarsest stage, besides the start itself; 0: the start only."""
    hypothesis_deg: float = 20.0
    """Rotation of each hypothesis away from the start (degrees, about the cameras' centroid)."""
    hypothesis_scales: tuple[float, ...] = ()
    """With hypotheses: every rotated candidate (and the start) also scaled by each factor about the cameras'
    centroid (e.g. 0.8 1.25: a log grid around the start's scale)."""
    hypotheses_kept: int = 3
    """Best-scoring hypotheses (the start included) optimised over the coarsest stage; the lowest end wins."""
    level_of_detail: float = 1.0
    """Merge the reference's Gaussians that are far below a render pixel, per voxel of this many render pixels
    at the nearest photo that sees them (registration/level_of_detail.py: the cost of a step follows the
    pixels, not the model's size); 0 renders every Gaussian as trained. 2 suits references of several hundred
    thousand Gaussians or more (from 100k to 1M Gaussians a step grew 2.2x at 2, 4.5x at 1) at a little detail: on the
    default scene the dense objective alone ended further from the truth at 2 on one of two meta-images; that is
    what `render_budget` does for large references only."""
    render_budget: int = 300_000
    """With `level_of_detail`: where the merged model still holds more Gaussians than this, the voxel doubles
    (at most twice: 4x `level_of_detail`) until it fits, so that the cost of a step is bounded whatever the
    reference's size (registration/visibility.py); 0 (or less): no budget. Models that fit are rendered exactly as at
    `level_of_detail` (every CPU reference this project trains: tens of thousands of Gaussians). At 400,000 a
    1M-Gaussian reference merged at 2 px (375k rendered) and its step cost 2.9-3.1x that of a 100k one; at 300,000 it
    merges at 4 px (146k) and costs 1.0-1.6x (two runs), its anchored registration ending as close (docs/measurements.md "All of it in one
    run")."""
    update_centre: Literal["cameras", "look-at"] = "cameras"
    """Point the update delta rotates and scales about: the centroid of the meta-image's cameras (DESIGN.md, the
    paper) or the point the photos look at (`MetaImage.look_at_under`). About the cameras, a rotation moves the
    scene across every photo just as a translation does (a long valley in delta that Adam crosses slowly);
    about the look-at point the two act on the images independently."""
    keypoint_weight: float = 0.0
    """Weight of the keypoint anchors (registration/keypoints.py): the initialiser's verified SIFT correspondences
    of the photos with the reference as a reprojection term, relative to the dense objective at each stage's
    start; 0 = the dense objective alone (the paper). Needs the reference's COLMAP model and images (found
    through the trained config, or --reference-colmap / --reference-images)."""
    keypoint_prealign_steps: int = 0
    """With keypoint anchors: steps of the keypoint term alone (no render, a few milliseconds each) that move the
    start to the keypoints' own optimum before the first stage; 0 = off."""
    refine_focal: bool = False
    """After the keypoint pre-alignment, fit one focal-length scale per COLMAP camera of the photos with keypoints
    jointly with the Sim(3), each held by the meta-image SfM's own uncertainty of that focal length at the keypoints'
    noise (render-free; `camera_fit.fit_cameras`, `camera_fit.intrinsics_priors`); every later stage renders the photos
    of those cameras with it, transform.json records it per photo and the aligned and merged models' cameras carry it.
    It moves focal lengths the SfM determined poorly (3-photo meta-images) and leaves well-determined ones; off = the
    SfM intrinsics as they are (the paper)."""
    refine_photo_poses: bool = False
    """In the same joint fit as `refine_focal` (with or without it), move each photo with keypoints inside the meta-image
    by a small rotation and centre shift, each held by a prior: `photo_pose_prior_scale` times the meta-image SfM's own
    uncertainty of that photo's orientation relative to the others (`relative_rotation_uncertainty`; the centre shift:
    the photo's median point depth times that angle, and along its optical axis, with `refine_focal`, also the depth
    change its focal uncertainty allows: `KeypointTerm.pose_sigma`). Every later stage renders the moved cameras, the result is the
    final Sim(3) composed with the one that maps the meta-image's cameras onto the moved ones
    (`geometry.alignment.align_cameras`), and transform.json records each photo's correction. For SfM models of a few
    photos whose relative poses are a fraction of a degree off (docs/measurements.md "Per-photo poses"); off = the meta-image is one
    rigid body (the paper)."""
    refine_distortion: bool = False
    """In the same joint fit, the first radial distortion coefficient k1 of each COLMAP camera of the photos with keypoints
    (models SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV), held by the meta-image SfM's own uncertainty of it at the
    keypoints' noise; the keypoints' rays are undistorted again with the fitted focal length and k1, every later stage
    renders against the photos undistorted with it, transform.json and the aligned model carry it. A 3-photo SfM can get k1 a few hundredths off
    (docs/measurements.md "Other splits and looks of the same real photos"); off = the SfM's distortion as it is (the paper)."""
    camera_fit: Literal["priors", "adjustment"] = "priors"
    """How `refine_photo_poses` fits the cameras (with `refine_focal` / `refine_distortion`). `priors`: the keypoints
    alone, each photo's focal length, k1, rotation and centre held by its own prior (`camera_fit.fit_jointly`).
    `adjustment`: one pycolmap bundle adjustment of the meta-image's own SfM observations with the keypoint anchors as
    constant points (registration/anchored_adjustment.py), which moves a photo's focal length, distortion, depth and
    orientation together as far as its own tracks allow; every photo moves, with anchors or not. On the 46 SIFT starts
    of the twelve real-photo benchmark scenes (fast-cpu) mean ΔR 0.129 -> 0.105° and ΔT 0.011 -> 0.010, the worst
    meta-image's ΔT 0.057 -> 0.021 (docs/measurements.md "The camera fit as a bundle adjustment"). Where the anchors
    leave the scale free (one photo's, or photos from one spot), a camera model has more distortion terms than k1, or
    a rig has several cameras, `priors` runs instead (`camera_fit.fit_cameras`)."""
    photo_pose_prior_scale: float = 1.0
    """`refine_photo_poses`' prior on each photo's rotation in units of the SfM's own standard deviation of it."""
    camera_fit_iterations: int = 100
    """At most this many Levenberg-Marquardt iterations (render-free; `camera_fit.fit_jointly`) for the joint fit of
    `refine_focal` / `refine_photo_poses` / `refine_distortion` (the real-photo meta-images converged in 7-10)."""
    prealigned_steps: Optional[int] = None
    """Steps of the main stage when the keypoint pre-alignment ran (it leaves the start within a fraction of a degree,
    where the dense objective needs neither the steps nor the learning rate that reach it from 5°); None: `steps`."""
    prealigned_lr: Optional[float] = None
    """Learning rate the main stage starts at after the keypoint pre-alignment (decaying to `lr_final`); None: `lr`."""
    refine_steps: int = 0
    """Steps of a last stage after the main one, from its result, with its own render teacher (`refine_teacher`);
    its learning rate starts at `refine_lr` and decays to `lr_final`. The verdict and the final losses stay the main
    stage's (the objective the verdict was calibrated on). 0 = no such stage (the paper)."""
    refine_teacher: Optional[Literal["offline", "dense-sift"]] = None
    """Weight-free descriptor the refine stage applies to the renders and the photos (teacher-on-render, whatever the
    main objective; see `render_teacher`); None: the main stage's objective and teacher."""
    refine_lr: float = 0.003
    """Learning rate the refine stage starts at."""
    refine_anchored: bool = True
    """Whether the refine stage also runs where keypoint anchors held the pose (False: only for the dense objective
    alone, where no SIFT correspondences were found)."""
    seed: int = 0
    backend: Literal["auto", "gsplat", "numba", "torch"] = "auto"


class SettingsRangeError(InputError):
    """A registration setting (a flag or a preset's key) outside the values it can take."""


COUNTS = ("steps", "images_per_step", "pyramid_steps", "hypotheses", "keypoint_prealign_steps", "camera_fit_iterations",
          "refine_steps", "seed", "prealigned_steps")
"""Whole numbers >= 0 (None allowed where the default is None)."""
POSITIVE = ("lr", "adam_eps", "render_scale", "near_plane", "refine_lr", "photo_pose_prior_scale", "lr_final", "prealigned_lr",
            "teacher_input_size")
"""Numbers > 0 (None allowed where the default is None)."""
NON_NEGATIVE = ("hypothesis_deg", "level_of_detail", "keypoint_weight")
"""Numbers >= 0."""
AT_LEAST_ONE = ("retrim_every", "hypotheses_kept")
"""Whole numbers >= 1."""


def check_ranges(settings: RegistrationSettings, preset: Optional[str] = None) -> None:
    """SettingsRangeError naming the first numeric setting that is not a finite number in its range (a NaN learning
    rate, a negative step count, a step count of 2.5 or "100" from a preset), and the `preset` it came from when
    given; the robust loss's own ranges are `robust.check_robust_settings`'."""

    def setting(name: str) -> str:
        return f"Registration preset {preset}: {name}" if preset else f"Registration setting {name} (--{name.replace('_', '-')})"

    for name in COUNTS + POSITIVE + NON_NEGATIVE:
        value = getattr(settings, name)
        if value is None and getattr(RegistrationSettings, name, 0) is None:
            continue
        whole = name in COUNTS or name == "teacher_input_size"
        is_number = isinstance(value, int) if whole else isinstance(value, (int, float))
        if isinstance(value, bool) or not is_number or not math.isfinite(value) or value < 0 or (name in POSITIVE and value == 0):
            kind = "a whole number" if whole else "a finite number"
            bound = "above 0" if name in POSITIVE else "of 0 or more"
            raise SettingsRangeError(f"{setting(name)} must be {kind} {bound}, got {value!r}.")
    for name in AT_LEAST_ONE:
        value = getattr(settings, name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise SettingsRangeError(f"{setting(name)} must be a whole number of 1 or more, got {value!r}.")
    if any(not isinstance(factor, int) or factor < 2 for factor in settings.pyramid):
        raise SettingsRangeError(f"{setting('pyramid')} must list whole numbers of 2 or more, got {list(settings.pyramid)}.")
    if any(not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0 for scale in settings.hypothesis_scales):
        raise SettingsRangeError(f"{setting('hypothesis_scales')} must list numbers above 0, got {list(settings.hypothesis_scales)}.")


def read_preset_text(name_or_path: str | Path) -> tuple[str, str]:
    """(where it was found, YAML text) of a preset name (see PRESETS) or a path; PresetError when neither exists."""
    if str(name_or_path) in PRESETS:
        resource = resources.files("sg_nerfstudio.registration") / "presets" / f"{name_or_path}.yaml"
        return f"'{name_or_path}' ({resource})", resource.read_text()
    path = Path(name_or_path)
    if not path.is_file():
        raise PresetError(f"Registration preset {name_or_path} is neither a preset name ({', '.join(PRESETS)}) nor an existing YAML file.")
    return str(path), path.read_text()


def load_preset(name_or_path: str | Path) -> RegistrationSettings:
    """The settings of a preset name or YAML file; unknown keys are refused."""
    where, text = read_preset_text(name_or_path)
    try:
        values = yaml.safe_load(text) or {}
    except yaml.YAMLError as error:
        raise PresetError(f"Registration preset {where} is not readable YAML ({type(error).__name__}).") from None
    if not isinstance(values, dict):
        raise PresetError(f"Registration preset {where} is not a mapping of setting names to values.")
    known = {f.name for f in dataclasses.fields(RegistrationSettings)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise PresetError(f"Registration preset {where} has unknown keys {unknown}; expected some of {sorted(known)}.")
    settings = RegistrationSettings(**values)
    check_ranges(settings, where)
    return settings
