"""The directory layout `sg-bench` reads, so users can drop in their own data (e.g. a WikiEarth-style release).

    <benchmark>/
        benchmark.json                      optional: {"scenes": [{"name": "<scene>"}, ...]} (order and
                                            selection); without it every sub-directory holding reference/
        <scene>/reference/images/           the reference capture (photos or renders of the whole landmark)
        <scene>/reference/colmap/sparse/0/  its COLMAP model (nerfstudio's colmap layout; sparse/0/ also accepted)
        <scene>/meta/<meta>/images/         one meta-image: photos ...
        <scene>/meta/<meta>/sparse/0/       ... its own COLMAP reconstruction (any frame and scale) ...
        <scene>/meta/<meta>/gt_transform.json   ... and the ground truth {"matrix": 4x4 meta -> reference world}

`sg-make-scene --preset benchmark` writes exactly this. Everything is checked before any training starts;
a wrong layout is one sentence naming the path and what was expected.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from sg_nerfstudio.errors import InputError, not_a_directory
from sg_nerfstudio.geometry.sim3 import Sim3

REFERENCE_MODELS = (Path("colmap") / "sparse" / "0", Path("sparse") / "0")


class BenchmarkLayoutError(InputError):
    """A benchmark directory that does not follow the layout."""


@dataclass
class BenchmarkMeta:
    name: str
    directory: Path
    ground_truth: Sim3  # meta -> reference world
    truth_residual: Optional[dict] = None
    """{"dR": degrees, "dT": reference units}: RMS over the photos of how far one Sim(3) leaves the meta-image's own SfM
    cameras from the solution's (gt_transform.json `residual_rotation_deg` / `residual_centre`, written by the
    real-photo scene builder); ΔR / ΔT differences below it are within the ground truth's own error. None where
    the file does not give it (synthetic scenes: exact)."""
    truth_disagreement: Optional[dict] = None
    """{"dR": degrees, "dT": reference units}: how far the point-based ground truth (the meta-image's SfM points fitted
    to its tracks triangulated with the solution's cameras, gt_transform.json `point_based`, `photos.scene.point_truth`)
    moves the meta-image's cameras from the camera-based one; None where the file does not give it."""


@dataclass
class BenchmarkScene:
    name: str
    directory: Path
    reference: Path  # the reference capture directory (images/ + COLMAP model)
    reference_model: Path  # its COLMAP model, relative to `reference`
    metas: list[BenchmarkMeta]


def read_benchmark(directory: Path) -> list[BenchmarkScene]:
    """Every scene of the benchmark at `directory`, checked against the layout."""
    directory = Path(directory)
    if not directory.is_dir():
        raise BenchmarkLayoutError(f"Benchmark directory {directory} {not_a_directory(directory)}; expected <benchmark>/<scene>/reference and meta/ (see sg-bench --help).")
    manifest = directory / "benchmark.json"
    if manifest.is_file():
        try:
            names = [entry["name"] for entry in json.loads(manifest.read_text())["scenes"]]
        except Exception as error:
            raise BenchmarkLayoutError(f"{manifest} is not JSON with a list \"scenes\" of {{\"name\": ...}} ({type(error).__name__}).") from None
    else:
        names = sorted(p.name for p in directory.iterdir() if (p / "reference").is_dir())
    if not names:
        raise BenchmarkLayoutError(f"Benchmark directory {directory} holds no scene; expected sub-directories with reference/ and meta/.")
    return [read_scene(directory / name) for name in names]


def read_benchmarks(directories: Sequence[Path]) -> list[BenchmarkScene]:
    """The scenes of several benchmark directories as one suite (e.g. synthetic and real-photo gap scenes side by
    side), in the order given; BenchmarkLayoutError when two scenes share a name (their runs and references would
    share one folder of the output)."""
    if not directories:
        raise BenchmarkLayoutError("No benchmark directory was given; expected one or more (e.g. from sg-make-scene --preset benchmark).")
    scenes: list[BenchmarkScene] = []
    for directory in directories:
        for scene in read_benchmark(directory):
            clash = next((other for other in scenes if other.name == scene.name), None)
            if clash is not None:
                raise BenchmarkLayoutError(
                    f"Scenes {clash.directory} and {scene.directory} share the name {scene.name!r}; expected every scene of the "
                    "benchmarks run together to have its own name (rename one folder, or run them with separate --output)."
                )
            scenes.append(scene)
    return scenes


def read_scene(directory: Path) -> BenchmarkScene:
    reference = directory / "reference"
    if not (reference / "images").is_dir():
        raise BenchmarkLayoutError(f"Scene {directory} has no reference/images/; expected the reference capture's images there.")
    models = [m for m in REFERENCE_MODELS if (reference / m).is_dir()]
    if not models:
        raise BenchmarkLayoutError(f"Scene {directory} has no reference COLMAP model; expected reference/colmap/sparse/0/ or reference/sparse/0/.")
    meta_root = directory / "meta"
    metas = sorted(p for p in meta_root.iterdir() if p.is_dir()) if meta_root.is_dir() else []
    if not metas:
        raise BenchmarkLayoutError(f"Scene {directory} has no meta-images; expected meta/<name>/ with images/, sparse/0/ and gt_transform.json.")
    return BenchmarkScene(directory.name, directory, reference, models[0], [read_meta(path) for path in metas])


def read_meta(directory: Path) -> BenchmarkMeta:
    path = directory / "gt_transform.json"
    try:
        record = json.loads(path.read_text())
        truth = Sim3.from_matrix(record["matrix"])
    except Exception as error:
        raise BenchmarkLayoutError(f"Meta-image {directory} needs gt_transform.json with a 4x4 similarity \"matrix\" (meta -> reference world) ({type(error).__name__}).") from None
    return BenchmarkMeta(directory.name, directory, truth, truth_residual(record), truth_disagreement(record))


def truth_residual(record: dict) -> Optional[dict]:
    """RMS of gt_transform.json's per-camera residuals {"dR", "dT"}, or None without (or with unusable) residuals."""
    try:
        rotation, centre = (np.asarray(record[key], dtype=np.float64) for key in ("residual_rotation_deg", "residual_centre"))
    except (KeyError, TypeError, ValueError):
        return None
    if rotation.size == 0 or centre.size == 0 or not (np.isfinite(rotation).all() and np.isfinite(centre).all()):
        return None
    return {"dR": float(np.sqrt(np.mean(rotation**2))), "dT": float(np.sqrt(np.mean(centre**2)))}


def truth_disagreement(record: dict) -> Optional[dict]:
    """{"dR", "dT"} between gt_transform.json's point-based and camera-based truths, or None without a usable one."""
    point_based = record.get("point_based")
    try:
        values = {"dR": float(point_based["delta_R_deg"]), "dT": float(point_based["delta_T"])}
    except (KeyError, TypeError, ValueError):
        return None
    return values if all(np.isfinite(v) and v >= 0 for v in values.values()) else None
