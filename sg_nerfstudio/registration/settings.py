"""How one meta-image is registered (`RegistrationSettings`, in groups), and the named presets shipped with the package.

Presets are YAML files in `sg_nerfstudio/registration/presets/` (installed with the package; `configs/register/`
links to them): `paper`, `fast-cpu`, `fast-cpu-features` and `wide-cpu`. A preset holds one mapping per group
(`optimiser: {steps: 100}`); `base: NAME` starts from another preset and changes only the keys it lists (the bench
variants of `configs/bench/`). Presets written before the groups existed (flat keys such as `refine_focal`) still load:
`LEGACY_KEYS` translates each old key to its group. Every command takes a preset with `--config NAME`,
`--config path.yaml` or `--config OUT/META/transform.json` (the settings a registration ran with, also one written
before the groups); `--GROUP.FIELD` flags override single values.
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal, Mapping, Optional

import yaml

from sg_nerfstudio.errors import InputError

ObjectiveKind = Literal["features", "teacher-on-render", "photometric"]
RobustRule = Literal["lts", "outlier-lts", "fixed-lts", "irls", "none"]
LossKind = Literal["l1", "l2"]
RenderTeacher = Literal["offline", "dense-sift", "hog-layout"]
PRESETS = ("paper", "fast-cpu", "fast-cpu-features", "wide-cpu")


class PresetError(InputError):
    """A registration preset that does not exist or does not hold registration settings."""


class SettingsRangeError(InputError):
    """A registration setting (a flag or a preset's key) outside the values it can take."""


@dataclass
class OptimiserSettings:
    """Adam on delta = (omega, nu, log s), the update of the Sim(3) (paper: 12000 steps at 1e-3)."""

    steps: int = 12000
    """Steps of the main stage."""
    lr: float = 1e-3
    """Learning rate the main stage starts at."""
    lr_final: Optional[float] = None
    """Exponential decay of the learning rate to this value at each stage's last step; None: constant (paper)."""
    adam_eps: float = 1e-8
    photos_per_step: int = 0
    """Photos rendered per step, drawn at random; 0: all of them (paper)."""
    update_centre: Literal["cameras", "look-at"] = "cameras"
    """Point delta rotates and scales about: the meta-image's camera centroid (paper) or the point its photos look at
    (rotation and translation then act on the images independently: a better-conditioned valley for Adam)."""


@dataclass
class ObjectiveSettings:
    """What a rendered photo is compared with."""

    kind: ObjectiveKind = "features"
    """features: the model's decoded feature field against the photos' teacher maps (paper); teacher-on-render: the
    teacher applied to the rendered RGB against the same maps; photometric: colours against the photos."""
    loss: LossKind = "l1"
    render_teacher: Optional[RenderTeacher] = None
    """teacher-on-render and photometric: the weight-free descriptor applied to renders and photos (offline:
    oriented-gradient histograms; dense-sift: kornia's dense RootSIFT); None: the reference's own teacher."""
    teacher_input_size: Optional[int] = None
    """Teacher input size for the photos; None: the one the reference was trained with (or the render teacher's own)."""
    render_scale: float = 2.0
    """Long side of the renders as a multiple of the teacher grid (never above the photo's long side, nor, for
    teacher-on-render, the teacher's input size)."""
    near_plane: float = 0.7
    """Near plane in dataparser units against floaters (paper: 0.7); lowered to half the nearest sparse-point depth of
    the meta-image so that it never cuts what the photos see."""


@dataclass
class RobustSettings:
    """Which photos count in a step: least-trimmed squares and its relatives (registration/robust.py)."""

    rule: RobustRule = "lts"
    """lts (paper: photos above the median loss are ignored), outlier-lts (only photos far above the others),
    fixed-lts (a fixed percentile), irls (Cauchy weights) or none."""
    lts_percentile: float = 50.0
    """lts / fixed-lts: photos whose loss is above this percentile of the previous losses are ignored."""
    outlier_z: float = 3.0
    """outlier-lts: photos whose loss is above median + outlier_z x the robust scale of the losses are ignored."""
    trim_after: float = 0.0
    """Fraction of each stage in which every photo counts before the rule trims (0: from the first step, paper)."""
    retrim_every: int = 1
    """Steps between re-decisions of which photos count; the steps between render only the counted photos (1: paper)."""


@dataclass
class CoarseToFineSettings:
    """Coarse stages before the main one: a wider basin of attraction from a start far off."""

    factors: tuple[int, ...] = ()
    """Each coarse stage runs the teacher at the main input size divided by a factor, coarsest first (e.g. 4 2)."""
    steps: int = 60
    """Steps of each coarse stage (learning rate: the main one times the factor, decaying tenfold)."""


@dataclass
class HypothesisSettings:
    """Several starts for the first stage (registration/hypotheses.py); the end the main stage's objective scores lowest wins."""

    count: int = 0
    """Rotations of the start about this many axes (a Fibonacci sphere), besides the start itself; 0: the start only."""
    rotation_deg: float = 20.0
    """Rotation of each hypothesis away from the start, about the cameras' centroid."""
    scales: tuple[float, ...] = ()
    """Each candidate also scaled by each factor about the cameras' centroid (e.g. 0.8 1.25)."""
    kept: int = 3
    """Best-scoring candidates optimised over the coarsest stage; the lowest end wins."""
    dense_start: bool = False
    """Where no keypoint anchors hold the meta-image: also optimise from the dense initialiser's start
    (initialisers/dense.py; it needs the reference's COLMAP model and images), so that a start in another basin, which
    SIFT cannot correct across a domain gap, still ends at the minimum the objective prefers (docs/gap-scenes.md)."""


@dataclass
class LevelOfDetailSettings:
    """How much of the reference is rendered (registration/level_of_detail.py, visibility.py)."""

    voxel_pixels: float = 1.0
    """Merge Gaussians far below a render pixel, per voxel of this many render pixels at the nearest photo that sees
    them, so that a step costs what its pixels cost; 0: every Gaussian as trained."""
    render_budget: int = 300_000
    """Where the merged model still holds more Gaussians than this, the voxel doubles (at most twice); 0: no budget."""


@dataclass
class AnchorSettings:
    """Keypoint anchors: the SIFT initialisers' verified 2D-3D matches as a reprojection term (registration/anchored_start)."""

    weight: float = 0.0
    """Weight of the anchors relative to the dense objective at each stage's start; 0: the dense objective alone (paper).
    Needs the reference's COLMAP model and images (through the trained config, or --reference-colmap / -images)."""
    prealign_steps: int = 0
    """Render-free steps on the anchors alone before the first render (pre-alignment); 0: none."""
    main_steps: Optional[int] = None
    """Steps of the main stage after a pre-alignment (it starts within a fraction of a degree); None: optimiser.steps."""
    main_lr: Optional[float] = None
    """Learning rate the main stage starts at after a pre-alignment; None: optimiser.lr."""


@dataclass
class CameraFitSettings:
    """After the pre-alignment, the meta-image's own cameras fitted to the anchors with the Sim(3) (render-free)."""

    focal: bool = False
    """Fit one focal-length scale per COLMAP camera, held by the SfM's own uncertainty of it."""
    photo_poses: bool = False
    """Move each photo inside the meta-image by a small rotation and centre shift, held by the SfM's own uncertainty;
    the result is the final Sim(3) composed with the one that maps the given cameras onto the moved ones."""
    distortion: bool = False
    """Fit each camera's first radial coefficient k1 (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV)."""
    solver: Literal["priors", "adjustment"] = "priors"
    """priors: the anchors alone, each camera parameter under its SfM prior (Levenberg-Marquardt); adjustment: one
    pycolmap bundle adjustment of the meta-image's own tracks with the anchors, used where it applies (the anchors fix
    the scale, cameras with at most k1); `priors` runs where it does not."""
    pose_prior_scale: float = 1.0
    """photo_poses: the prior on each photo's rotation in units of the SfM's standard deviation of it."""
    iterations: int = 100
    """At most this many Levenberg-Marquardt iterations of the priors fit."""


@dataclass
class LastStageSettings:
    """A last rendered stage after the main one, with its own weight-free teacher (the verdict stays the main stage's)."""

    steps: int = 0
    """Steps of the last stage; 0: none (paper)."""
    teacher: Optional[RenderTeacher] = None
    """Descriptor applied to renders and photos (teacher-on-render); None: the main stage's objective and teacher."""
    lr: float = 0.003
    """Learning rate the last stage starts at (decaying to optimiser.lr_final)."""
    with_anchors: bool = True
    """Whether it also runs where keypoint anchors held the pose (False: only for the dense objective alone)."""


@dataclass
class RegistrationSettings:
    """How one meta-image is registered (defaults: the paper's settings)."""

    optimiser: OptimiserSettings = field(default_factory=OptimiserSettings)
    objective: ObjectiveSettings = field(default_factory=ObjectiveSettings)
    robust: RobustSettings = field(default_factory=RobustSettings)
    coarse_to_fine: CoarseToFineSettings = field(default_factory=CoarseToFineSettings)
    hypotheses: HypothesisSettings = field(default_factory=HypothesisSettings)
    level_of_detail: LevelOfDetailSettings = field(default_factory=LevelOfDetailSettings)
    anchors: AnchorSettings = field(default_factory=AnchorSettings)
    camera_fit: CameraFitSettings = field(default_factory=CameraFitSettings)
    last_stage: LastStageSettings = field(default_factory=LastStageSettings)
    seed: int = 0
    """Seed of the photo batches and of the hypotheses' axes."""
    backend: Literal["auto", "gsplat", "numba", "torch"] = "auto"
    """Rasterizer: gsplat's CUDA kernels on CUDA tensors, the numba CPU compositor, or the pure-torch one."""

    def changed(self, **changes: Any) -> "RegistrationSettings":
        """A copy with `changes`: a group name with a mapping of its fields (`optimiser={"steps": 10}`), or a top-level
        field with its value (`seed=3`)."""
        values = {}
        for name, value in changes.items():
            if name in GROUPS:
                values[name] = dataclasses.replace(getattr(self, name), **value)
            else:
                values[name] = value
        return dataclasses.replace(self, **values)


GROUPS = {name: kind for name, kind in typing.get_type_hints(RegistrationSettings).items() if dataclasses.is_dataclass(kind)}
"""Group name -> its settings class, in the order of `RegistrationSettings`."""

LEGACY_KEYS = {
    "steps": "optimiser.steps", "lr": "optimiser.lr", "lr_final": "optimiser.lr_final", "adam_eps": "optimiser.adam_eps",
    "images_per_step": "optimiser.photos_per_step", "update_centre": "optimiser.update_centre",
    "objective": "objective.kind", "loss": "objective.loss", "render_teacher": "objective.render_teacher",
    "teacher_input_size": "objective.teacher_input_size", "render_scale": "objective.render_scale", "near_plane": "objective.near_plane",
    "robust": "robust.rule", "lts_percentile": "robust.lts_percentile", "outlier_z": "robust.outlier_z", "trim_after": "robust.trim_after",
    "retrim_every": "robust.retrim_every",
    "pyramid": "coarse_to_fine.factors", "pyramid_steps": "coarse_to_fine.steps",
    "hypotheses": "hypotheses.count", "hypothesis_deg": "hypotheses.rotation_deg", "hypothesis_scales": "hypotheses.scales",
    "hypotheses_kept": "hypotheses.kept", "dense_start": "hypotheses.dense_start",
    "level_of_detail": "level_of_detail.voxel_pixels", "render_budget": "level_of_detail.render_budget",
    "keypoint_weight": "anchors.weight", "keypoint_prealign_steps": "anchors.prealign_steps", "prealigned_steps": "anchors.main_steps",
    "prealigned_lr": "anchors.main_lr",
    "refine_focal": "camera_fit.focal", "refine_photo_poses": "camera_fit.photo_poses", "refine_distortion": "camera_fit.distortion",
    "camera_fit": "camera_fit.solver", "photo_pose_prior_scale": "camera_fit.pose_prior_scale", "camera_fit_iterations": "camera_fit.iterations",
    "refine_steps": "last_stage.steps", "refine_teacher": "last_stage.teacher", "refine_lr": "last_stage.lr",
    "refine_anchored": "last_stage.with_anchors",
}
"""The flat keys of presets (and transform.json's "settings") written before the groups -> "group.field"."""

RANGES = {
    "count": ("optimiser.steps", "optimiser.photos_per_step", "coarse_to_fine.steps", "hypotheses.count", "anchors.prealign_steps",
              "anchors.main_steps", "camera_fit.iterations", "last_stage.steps", "seed", "objective.teacher_input_size"),
    "positive": ("optimiser.lr", "optimiser.adam_eps", "optimiser.lr_final", "objective.render_scale", "objective.near_plane",
                 "anchors.main_lr", "camera_fit.pose_prior_scale", "last_stage.lr", "objective.teacher_input_size"),
    "non-negative": ("hypotheses.rotation_deg", "level_of_detail.voxel_pixels", "anchors.weight"),
    "at-least-one": ("robust.retrim_every", "hypotheses.kept"),
}
"""Numeric settings by range: counts are whole numbers >= 0, positive numbers > 0, non-negative >= 0, at-least-one whole
numbers >= 1 (None passes where the default is None). The robust rule's own ranges are `robust.check_robust_settings`'."""


def literal_choices() -> dict[str, tuple]:
    """{"group.field": the values it may take} of every setting typed as a Literal (Optional ones also take None)."""
    choices = {}
    for group, kind in [*GROUPS.items(), ("", RegistrationSettings)]:
        for name, hint in typing.get_type_hints(kind).items():
            options = [arg for arg in typing.get_args(hint) if arg is not type(None)]
            values = typing.get_args(options[0]) if len(options) == 1 and typing.get_origin(options[0]) is Literal else (
                typing.get_args(hint) if typing.get_origin(hint) is Literal else ())
            if values:
                optional = type(None) in typing.get_args(hint)
                choices[f"{group}.{name}" if group else name] = tuple(values) + ((None,) if optional else ())
    return choices


CHOICES = literal_choices()
"""Every setting with a fixed set of values (a preset is not parsed by tyro, so these are checked here)."""
SWITCHES = tuple(f"{group}.{name}" for group, kind in GROUPS.items() for name, hint in typing.get_type_hints(kind).items() if hint is bool)
"""Every on/off setting."""


def value_at(settings: RegistrationSettings, path: str) -> Any:
    """The setting at "group.field" (or a top-level "field")."""
    group, _, name = path.rpartition(".")
    return getattr(getattr(settings, group) if group else settings, name)


def flag(path: str) -> str:
    """The command-line flag of a setting path: "camera_fit.focal" -> "--camera-fit.focal"."""
    return "--" + path.replace("_", "-")


def check_ranges(settings: RegistrationSettings, preset: Optional[str] = None) -> None:
    """SettingsRangeError naming the first numeric setting that is not a finite number in its range (a NaN learning
    rate, a negative step count, a step count of 2.5 or "100" from a preset), and the `preset` it came from."""
    default = RegistrationSettings()

    def setting(path: str) -> str:
        return f"Registration preset {preset}: {path}" if preset else f"Registration setting {path} ({flag(path)})"

    for kind in ("count", "positive", "non-negative"):
        for path in RANGES[kind]:
            value = value_at(settings, path)
            if value is None and value_at(default, path) is None:
                continue
            whole = path in RANGES["count"]
            is_number = isinstance(value, int) if whole else isinstance(value, (int, float))
            if isinstance(value, bool) or not is_number or not math.isfinite(value) or value < 0 or (kind == "positive" and value == 0):
                bound = "above 0" if path in RANGES["positive"] else "of 0 or more"
                raise SettingsRangeError(f"{setting(path)} must be {'a whole number' if whole else 'a finite number'} {bound}, got {value!r}.")
    for path in RANGES["at-least-one"]:
        value = value_at(settings, path)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise SettingsRangeError(f"{setting(path)} must be a whole number of 1 or more, got {value!r}.")
    budget = settings.level_of_detail.render_budget
    if not isinstance(budget, int) or isinstance(budget, bool):
        raise SettingsRangeError(f"{setting('level_of_detail.render_budget')} must be a whole number (0 or less: no budget), got {budget!r}.")
    for path in SWITCHES:
        if not isinstance(value_at(settings, path), bool):
            raise SettingsRangeError(f"{setting(path)} must be true or false, got {value_at(settings, path)!r}.")
    for path, choices in CHOICES.items():
        value = value_at(settings, path)
        if value not in choices:
            raise SettingsRangeError(f"{setting(path)} must be one of {', '.join(str(c) for c in choices)}, got {value!r}.")
    factors, scales = settings.coarse_to_fine.factors, settings.hypotheses.scales
    if any(not isinstance(factor, int) or isinstance(factor, bool) or factor < 2 for factor in factors):
        raise SettingsRangeError(f"{setting('coarse_to_fine.factors')} must list whole numbers of 2 or more, got {list(factors)}.")
    if any(not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0 for scale in scales):
        raise SettingsRangeError(f"{setting('hypotheses.scales')} must list numbers above 0, got {list(scales)}.")


def read_preset_text(name_or_path: str | Path) -> tuple[str, str]:
    """(where it was found, YAML text) of a preset name (see PRESETS) or a path; PresetError when neither exists."""
    if str(name_or_path) in PRESETS:
        resource = resources.files("sg_nerfstudio.registration") / "presets" / f"{name_or_path}.yaml"
        return f"'{name_or_path}' ({resource})", resource.read_text()
    path = Path(name_or_path)
    if not path.is_file():
        raise PresetError(f"Registration preset {name_or_path} is neither a preset name ({', '.join(PRESETS)}) nor an existing YAML file.")
    return str(path), path.read_text()


def read_preset_values(name_or_path: str | Path) -> tuple[str, dict]:
    """(where it was found, its mapping as written: groups, top-level fields, maybe `base`); PresetError when it is
    not YAML or not a mapping. A registration's transform.json gives the settings it recorded."""
    where, text = read_preset_text(name_or_path)
    try:
        values = (json.loads(text) if text.lstrip().startswith("{") else yaml.safe_load(text)) or {}  # YAML reads 1e-08 as text
    except (yaml.YAMLError, ValueError) as error:
        raise PresetError(f"Registration preset {where} is not readable YAML ({type(error).__name__}).") from None
    if not isinstance(values, dict):
        raise PresetError(f"Registration preset {where} is not a mapping of setting names to values.")
    if isinstance(values.get("settings"), dict) and "matrix" in values:  # a transform.json: the settings it ran with
        return where, values["settings"]
    return where, values


def grouped(values: Mapping, where: str) -> dict[str, Any]:
    """`values` (a preset's mapping without `base`) as {group: {field: value}, top-level field: value}, old flat keys
    translated by LEGACY_KEYS; PresetError naming an unknown key (and the key it is now, where it was renamed) or a
    setting given twice."""
    result: dict[str, Any] = {}
    written: dict[str, str] = {}

    def put(path: str, value: Any, as_written: str) -> None:
        if path in written:
            raise PresetError(f"Registration preset {where} sets {path} twice (as {written[path]} and as {as_written}).")
        written[path] = as_written
        group, _, name = path.rpartition(".")
        (result.setdefault(group, {}) if group else result)[name] = value

    for key, value in values.items():
        if key in GROUPS and not (key in LEGACY_KEYS and not isinstance(value, Mapping)):  # "objective: features" is a flat key
            if not isinstance(value, Mapping):
                raise PresetError(f"Registration preset {where}: {key} must be a mapping of its settings, got {value!r}.")
            known = {f.name for f in dataclasses.fields(GROUPS[key])}
            for name, inner in value.items():
                if name not in known:
                    renamed = f" ({name} is now {LEGACY_KEYS[name]})" if name in LEGACY_KEYS else ""
                    raise PresetError(f"Registration preset {where} has no setting {key}.{name}{renamed}; {key} holds {', '.join(sorted(known))}.")
                put(f"{key}.{name}", inner, f"{key}.{name}")
        elif key in ("seed", "backend"):
            put(key, value, key)
        elif key in LEGACY_KEYS:
            put(LEGACY_KEYS[key], value, key)
        else:
            raise PresetError(
                f"Registration preset {where} has an unknown key {key!r}; expected the groups {', '.join(GROUPS)}, seed, backend or base."
            )
    return result


def from_values(values: Mapping, where: str, base: Optional[RegistrationSettings] = None) -> RegistrationSettings:
    """`base` (default: the paper's settings) changed by a preset's `values` (grouped or flat, see `grouped`); YAML
    lists become tuples."""
    changes = {
        key: {name: tuple(v) if isinstance(v, list) else v for name, v in value.items()} if key in GROUPS else value
        for key, value in grouped(values, where).items()
    }
    try:
        return (base or RegistrationSettings()).changed(**changes)
    except TypeError as error:
        raise PresetError(f"Registration preset {where} could not be read ({error}).") from None


def load_preset(name_or_path: str | Path, _seen: tuple[str, ...] = ()) -> RegistrationSettings:
    """The settings of a preset name or YAML file: its `base` preset (if any) changed by its keys; unknown keys and
    values out of range are refused with one sentence."""
    where, values = read_preset_values(name_or_path)
    base = None
    if "base" in values:
        base_name = values.pop("base")
        if not isinstance(base_name, str):
            raise PresetError(f"Registration preset {where}: base must name a preset ({', '.join(PRESETS)}) or a YAML file, got {base_name!r}.")
        if base_name not in PRESETS:  # a file, relative to the preset that names it
            base_name = str(Path(str(name_or_path)).parent / base_name)
        if base_name in _seen + (str(name_or_path),):
            raise PresetError(f"Registration preset {where}: base {base_name} leads back to itself.")
        base = load_preset(base_name, _seen + (str(name_or_path),))
    settings = from_values(values, where, base)
    check_ranges(settings, where)
    return settings


def as_record(settings: RegistrationSettings) -> dict:
    """The settings as nested plain values (what transform.json and the benchmark records hold)."""
    return dataclasses.asdict(settings)
