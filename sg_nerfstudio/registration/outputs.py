"""Everything ns-register-meta writes for one meta-image, into a directory that appears atomically.

    transform.json   Sim(3) meta -> reference world (matrix, scale, quaternion, translation), the initial
                     transform, the verdict (registered | uncertain | failed) with its reasons and evidence,
                     final trimmed loss, steps, wall time, settings, the optimised hypotheses (if any), the
                     scale search when the keypoint anchors left the scale free (one photo's, or those of photos
                     from one spot: `scale_search`, else null), per
                     photo its losses, the focal_scale it was rendered with and (with `camera_fit.photo_poses`) its
                     pose_correction: how far its camera was moved from where the Sim(3) puts it (null: not moved)
                     and (with `camera_fit.distortion`) its camera's radial_k1 (null: as the SfM found it)
    aligned/         the meta-image's COLMAP model in the reference world frame as the registration placed it
                     (`registered_reconstruction`): moved by the Sim(3), with the focal lengths, k1 and poses it
                     fitted (`camera_fit.focal` / `.distortion` / `.photo_poses`) and then every track
                     triangulated again with those cameras
    losses.csv       per step and photo: loss, whether LTS kept it, its weight, the stage (coarse-<size> | main)
    report/          loss_curve.png, ignored_histogram.png, comparisons/*.png (before | after, each titled; top
                     half: reference model rendered at the photo's pose, bottom half: the photo; labelled)
    metrics.json     with --gt: ΔR, ΔT, accurate/outlier before and after
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Optional

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
import torch  # noqa: E402

from sg_nerfstudio.atomic import atomic_directory  # noqa: E402
from sg_nerfstudio.geometry.frames import viewmat  # noqa: E402
from sg_nerfstudio.geometry.meta_image import MetaImage  # noqa: E402
from sg_nerfstudio.geometry.sim3 import Sim3  # noqa: E402
from sg_nerfstudio.registration.merge import aligned_reconstruction  # noqa: E402
from sg_nerfstudio.registration.metrics import PoseErrors  # noqa: E402
from sg_nerfstudio.registration.optimize import RegistrationResult  # noqa: E402
from sg_nerfstudio.registration.reference import ReferenceModel  # noqa: E402

Array = np.ndarray
COMPARISON_LONG_SIDE = 320


def write_outputs(
    target: Path,
    reference: ReferenceModel,
    meta: MetaImage,
    result: RegistrationResult,
    errors: Optional[dict[str, PoseErrors]] = None,
    overwrite: bool = False,
    aligned: Optional[pycolmap.Reconstruction] = None,
) -> Path:
    """Write all outputs into `target` (created atomically via a temporary sibling); `aligned`: the
    `registered_reconstruction` of `meta` and `result` when the caller has it already (merged/ reuses it)."""
    aligned = aligned if aligned is not None else registered_reconstruction(meta, result)
    meta = meta.with_focal_scales(result.focal_scales).with_radial_distortion(result.radial_k1)  # the intrinsics it rendered with
    with atomic_directory(target, overwrite=overwrite) as staging:
        _write_transform(staging, reference, meta, result)
        (staging / "aligned").mkdir()
        aligned.write_binary(str(staging / "aligned"))
        _write_losses(staging / "losses.csv", result)
        report = staging / "report"
        report.mkdir()
        _plot_losses(report / "loss_curve.png", result)
        _plot_ignored(report / "ignored_histogram.png", result)
        _write_comparisons(report / "comparisons", reference, meta, result)
        if errors is not None:
            (staging / "metrics.json").write_text(json.dumps({k: v.as_dict() for k, v in errors.items()}, indent=2))
    return target


def _write_transform(directory: Path, reference: ReferenceModel, meta: MetaImage, result: RegistrationResult) -> None:
    record = result.transform.as_record()
    camera_of = {photo.name: int(photo.camera.camera_id) for photo in meta.photos}
    record.update({
        "initial": result.initial_transform.as_record(),
        "verdict": result.verdict.label,
        "verdict_reasons": result.verdict.reasons,
        "verdict_evidence": result.verdict.as_record()["evidence"],
        "meta_image": str(meta.directory),
        "reference_config": str(reference.config_path),
        "reference_checkpoint": str(reference.checkpoint_path),
        "final_trimmed_loss": result.final_trimmed_loss,
        "steps": result.steps,
        "wall_time_s": round(result.wall_time_s, 3),
        "time_split_s": {k: round(v, 3) for k, v in result.timings.items()},
        "effective_near_plane": result.near_plane,
        "rendered_model": result.rendered_model,
        "hypotheses": result.hypotheses,
        "scale_search": result.scale_search,
        "settings": result.settings,
        "photos": [
            {"name": n, "initial_loss": float(a), "final_loss": float(b), "ignored_fraction": float(c), "initial_coverage": float(d),
             "focal_scale": result.focal_scales.get(n, 1.0), "pose_correction": result.pose_corrections.get(n),
             "radial_k1": result.radial_k1.get(camera_of.get(n, -1))}
            for n, a, b, c, d in zip(result.photo_names, result.initial_losses, result.final_losses, result.ignored_fraction, result.coverage)
        ],
    })
    (directory / "transform.json").write_text(json.dumps(record, indent=2))


def registered_reconstruction(meta: MetaImage, result: RegistrationResult) -> pycolmap.Reconstruction:
    """The meta-image's COLMAP model (`meta` as given to the registration) where the registration put it: moved by
    `result.transform` into the reference world, its cameras with the focal lengths and k1 the registration fitted, the
    photos it moved at their fitted poses, and, if any camera changed, every track triangulated again with the new
    cameras (`merge.aligned_reconstruction`). aligned/ and merged/ are made of it."""
    refined = meta.with_focal_scales(result.focal_scales).with_radial_distortion(result.radial_k1)
    changed = bool(result.focal_scales or result.radial_k1 or result.photo_poses)
    return aligned_reconstruction(refined.reconstruction, result.transform, refined.camera_focal_scales(), result.photo_poses, retriangulate=changed)


def _write_losses(path: Path, result: RegistrationResult) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["step", "image", "loss", "kept", "weight", "stage"])
        writer.writeheader()
        writer.writerows(result.history)


def _plot_losses(path: Path, result: RegistrationResult) -> None:
    steps = np.array([row["step"] for row in result.history], dtype=np.int64)  # none when no stage took a step
    losses = np.array([row["loss"] for row in result.history], dtype=np.float64)
    kept = np.array([row["kept"] for row in result.history], dtype=bool)
    all_mean = np.bincount(steps, weights=losses) / np.maximum(np.bincount(steps), 1)
    kept_mean = np.bincount(steps, weights=losses * kept) / np.maximum(np.bincount(steps, weights=kept.astype(float)), 1)
    rendered = np.bincount(steps)
    every = np.flatnonzero(rendered == rendered.max()) if len(rendered) else rendered  # steps between re-decisions render fewer
    figure, axis = plt.subplots(figsize=(6, 3.5))
    axis.plot(every, all_mean[every], label="all photos in the step", alpha=0.6)
    axis.plot(kept_mean, label="kept by the robust loss")
    for row in stage_starts(result.history)[1:]:  # coarse-to-fine: each stage has its own loss scale
        axis.axvline(row["step"], color="grey", linestyle=":")
        axis.annotate(row["stage"], (row["step"], 1.0), xycoords=("data", "axes fraction"), va="top", fontsize=7)
    axis.set_xlabel("step")
    axis.set_ylabel(f"{result.settings['objective']['loss']} {result.settings['objective']['kind']} loss")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def stage_starts(history: list[dict]) -> list[dict]:
    """The first row of each stage in a registration's history."""
    return [row for previous, row in zip([None] + history[:-1], history) if previous is None or previous["stage"] != row["stage"]]


def _plot_ignored(path: Path, result: RegistrationResult) -> None:
    figure, axis = plt.subplots(figsize=(6, 3.5))
    axis.hist(result.ignored_fraction, bins=np.linspace(0, 1, 11), edgecolor="black")
    axis.set_xlabel("fraction of steps in which the photo was ignored")
    axis.set_ylabel("photos")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def render_rgb_at_photo(reference: ReferenceModel, cam_from_meta: Array, K: Array, width: int, height: int, meta_to_world: Sim3, near_plane: float) -> Array:
    """[H, W, 3] uint8 colour render of the reference model from a meta camera moved by `meta_to_world`."""
    meta_to_dataparser = (reference.world_to_dataparser @ meta_to_world).to_torch()
    camera = viewmat(meta_to_dataparser.move_camera(torch.from_numpy(cam_from_meta))).float()
    with torch.no_grad():
        rgb, _ = reference.render_rgb(camera[None], torch.from_numpy(K).float()[None], width, height, near_plane)
    return (rgb[0].numpy() * 255 + 0.5).astype(np.uint8)


def _write_comparisons(directory: Path, reference: ReferenceModel, meta: MetaImage, result: RegistrationResult, count: int = 4) -> None:
    """For the photos with the lowest and highest final loss: [before | after] (the paper's figures), each panel
    the model's render in the top half over the photo in the bottom half, every part labelled in the image."""
    directory.mkdir()
    order = np.argsort(result.final_losses)
    chosen = list(dict.fromkeys([*order[: count // 2], *order[::-1][: count - count // 2]]))
    for index in chosen:
        photo = meta.photos[int(index)]
        image, K = photo.load_resized(COMPARISON_LONG_SIDE)
        height, width = image.shape[:2]
        panels = []
        for transform, title in ((result.initial_transform, "before (initial transform)"), (result.transform, "after (registered)")):
            render = render_rgb_at_photo(reference, photo.cam_from_world, K, width, height, transform, result.near_plane)
            panel = image.copy()
            panel[: height // 2] = render[: height // 2]
            panel[height // 2 - 1 : height // 2 + 1] = 255
            _label(panel, "model render", (0, 0))
            _label(panel, "photo", (0, height // 2 + 1))
            panels.append(np.concatenate([_title_strip(title, width), panel], axis=0))
        separator = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
        combined = np.concatenate([panels[0], separator, panels[1]], axis=1)
        cv2.imwrite(str(comparison_path(directory, photo.name)), cv2.cvtColor(combined, cv2.COLOR_RGB2BGR))


def comparison_path(directory: Path, photo_name: str) -> Path:
    """Where the comparison of the photo named `photo_name` (its COLMAP image name) goes: one flat file per photo, its
    folders joined by "__" so that photos of different sub-folders with one file name ("cam1/0001.jpg",
    "cam2/0001.jpg") do not overwrite each other."""
    return directory / f"{'__'.join(Path(photo_name).with_suffix('').parts)}_before_after.png"


LABEL_FONT = cv2.FONT_HERSHEY_SIMPLEX
TITLE_HEIGHT = 22


def _title_strip(text: str, width: int) -> Array:
    """[TITLE_HEIGHT, width, 3] white strip with `text` in black."""
    strip = np.full((TITLE_HEIGHT, width, 3), 255, np.uint8)
    cv2.putText(strip, text, (4, TITLE_HEIGHT - 7), LABEL_FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def _label(panel: Array, text: str, corner: tuple[int, int]) -> None:
    """White `text` on a black box at `corner` (x, y of its top-left) of an [H, W, 3] panel, in place."""
    (text_width, text_height), baseline = cv2.getTextSize(text, LABEL_FONT, 0.4, 1)
    x, y = corner
    cv2.rectangle(panel, (x, y), (x + text_width + 6, y + text_height + baseline + 4), (0, 0, 0), thickness=-1)
    cv2.putText(panel, text, (x + 3, y + text_height + 2), LABEL_FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
