"""What sg-view-registration shows, read from disk: ns-register-meta's result directories, the meta-images they
name and optional ground truths, each as a `Registration` (the transforms to draw, per kind).

    initial       the transform registration started from ("initial" in transform.json)
    final         the registered transform ("matrix" in transform.json)
    ground_truth  only with --gt (ns-register-meta does not record which --gt it was given)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rich.console import Console

from sg_nerfstudio.errors import InputError, not_a_directory
from sg_nerfstudio.geometry.meta_image import MetaImage, load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3


class RegistrationViewError(InputError):
    """An input of sg-view-registration that cannot be shown."""


@dataclass
class Registration:
    """One meta-image's ns-register-meta result, with the transforms to draw.

    Attributes:
        name: meta-image name (the result directory's name).
        directory: the result directory holding transform.json.
        meta: the meta-image (photos, COLMAP cameras in the meta frame).
        transforms: kind ("initial", "final", "ground_truth") -> Sim3 meta -> reference world.
        summary: one markdown paragraph (steps, loss, ΔR / ΔT from metrics.json when present).
    """

    name: str
    directory: Path
    meta: MetaImage
    transforms: dict[str, Sim3]
    summary: str


def find_registration_dirs(paths: tuple[Path, ...]) -> list[Path]:
    """Result directories holding transform.json: each path itself, or else its sub-directories that do."""
    found = []
    for path in paths:
        if (path / "transform.json").is_file():
            found.append(path)
            continue
        if not path.is_dir():
            raise RegistrationViewError(
                f"Registration directory {path} {not_a_directory(path)}; expected <output-dir>/<meta-image>/ as written by ns-register-meta."
            )
        children = sorted(p for p in path.iterdir() if not p.name.startswith(".") and (p / "transform.json").is_file())
        if not children:
            raise RegistrationViewError(
                f"Registration directory {path} has no transform.json (nor do its sub-directories); expected "
                "<output-dir>/<meta-image>/ as written by ns-register-meta."
            )
        found.extend(children)
    return found


def per_registration(values: tuple[Path, ...], count: int, flag: str) -> list[Optional[Path]]:
    """One value per registration (or None for all when the flag was not given)."""
    if not values:
        return [None] * count
    if len(values) != count:
        raise RegistrationViewError(f"{flag} was given {len(values)} times for {count} meta-images; expected 0 or {count}.")
    return list(values)


def read_matrix(value, source: str) -> Sim3:
    """A Sim3 from a JSON value (a 4x4 list); `source` names it in the error."""
    try:
        return Sim3.from_matrix(value)
    except (TypeError, ValueError) as error:
        raise RegistrationViewError(f"{source} is not a 4x4 similarity transform ({error}).") from None


def read_json(path: Path, what: str) -> dict:
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise RegistrationViewError(f"{what} {path} does not exist.") from None
    except (OSError, ValueError) as error:
        raise RegistrationViewError(f"{what} {path} is not readable JSON ({type(error).__name__}).") from None
    if not isinstance(record, dict):
        raise RegistrationViewError(f"{what} {path} is not a JSON object with a \"matrix\".")
    return record


def read_registration(directory: Path, meta_dir: Optional[Path], gt_path: Optional[Path]) -> Registration:
    """Read transform.json (+ metrics.json), the meta-image it names (or `meta_dir`) and the ground truth."""
    transform_path = directory / "transform.json"
    record = read_json(transform_path, "Registration file")
    if "matrix" not in record or "matrix" not in (record.get("initial") or {}):
        raise RegistrationViewError(f"{transform_path} lacks \"matrix\" or \"initial\".\"matrix\"; expected a transform.json written by ns-register-meta.")
    transforms = {
        "initial": read_matrix(record["initial"]["matrix"], f"\"initial\" in {transform_path}"),
        "final": read_matrix(record["matrix"], f"\"matrix\" in {transform_path}"),
    }
    if gt_path is not None:
        transforms["ground_truth"] = read_matrix(read_json(gt_path, "Ground-truth file").get("matrix"), f"Ground truth {gt_path}")
    if meta_dir is None:
        if "meta_image" not in record:
            raise RegistrationViewError(f"{transform_path} does not record its meta-image directory; pass --meta-image.")
        meta_dir = Path(record["meta_image"])
        if not meta_dir.is_dir():
            raise RegistrationViewError(f"Meta-image directory {meta_dir} recorded in {transform_path} does not exist; pass --meta-image with its current location.")
    scales = {photo["name"]: float(photo["focal_scale"]) for photo in record.get("photos") or [] if isinstance(photo, dict) and "focal_scale" in photo}
    meta = load_meta_image(meta_dir).with_focal_scales(scales)  # the panel renders with the focal lengths registration used
    return Registration(directory.name, directory, meta, transforms, registration_summary(directory, record, len(meta.photos)))


def registration_summary(directory: Path, record: dict, photo_count: int) -> str:
    """Markdown: photos, steps, final trimmed loss, and ΔR / ΔT before -> after when metrics.json exists."""
    text = f"{photo_count} photos, {record.get('steps', '?')} steps, trimmed loss {float(record.get('final_trimmed_loss', float('nan'))):.4f}"
    metrics_path = directory / "metrics.json"
    if metrics_path.is_file():
        try:
            metrics = json.loads(metrics_path.read_text())
            before, after = metrics["before"], metrics["after"]
            text += (
                f"  \nΔR {before['delta_R_deg']:.2f}° → {after['delta_R_deg']:.2f}°, "
                f"ΔT {before['delta_T']:.3f} → {after['delta_T']:.3f} (metrics.json)"
            )
        except (OSError, ValueError, KeyError, TypeError):
            text += "  \n(metrics.json unreadable)"
    return text




def read_registrations(
    paths: tuple[Path, ...], meta_images: tuple[Path, ...], gts: tuple[Path, ...], load_config: Path, console: Console,
) -> list[Registration]:
    """Every registration under `paths` (see `find_registration_dirs`), with --meta-image / --gt per registration."""
    directories = find_registration_dirs(paths)
    names = [d.name for d in directories]
    if len(set(names)) != len(names):
        raise RegistrationViewError(f"Registration directories must have distinct names (one meta-image each), got {names}.")
    metas = per_registration(meta_images, len(directories), "--meta-image")
    truths = per_registration(gts, len(directories), "--gt")
    registrations = [read_registration(d, m, g) for d, m, g in zip(directories, metas, truths)]
    for registration in registrations:
        recorded = json.loads((registration.directory / "transform.json").read_text()).get("reference_config")
        if recorded and Path(recorded).resolve() != Path(load_config).resolve():
            console.print(f"[yellow]{registration.name} was registered against {recorded}, not {load_config}.[/yellow]", soft_wrap=True)
        gt_note = "with ground truth" if "ground_truth" in registration.transforms else "no ground truth (--gt)"
        console.print(f"{registration.name}: {len(registration.meta.photos)} photos from {registration.meta.directory}, {gt_note}", soft_wrap=True)
    return registrations
