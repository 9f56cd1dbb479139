"""The folder of photo/render pairs the teacher benchmark reads (`sg-bench teacher PAIRS`).

    <pairs>/<landmark>/photos/<name>.jpg     a photo (any format OpenCV reads: jpg, png, ...)
    <pairs>/<landmark>/renders/<name>.jpg    the reference rendered at that photo's true pose, same name and size
or, for a single landmark, `<pairs>/photos/` and `<pairs>/renders/` directly (the landmark is named after the folder).

A pixel of the photo and the same pixel of its render should show the same scene point. Every photo needs its render;
a render without a photo is ignored. Everything is checked before any teacher runs: a wrong layout is one sentence
naming the path and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sg_nerfstudio.errors import InputError, not_a_directory

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
MIN_SIDE = 64
"""Smallest image side (pixels) the benchmark's hypotheses fit in: a 46-pixel crop, shifted, rotated and zoomed."""


class PairsError(InputError):
    """A pairs folder that does not hold photo/render pairs in the layout above."""


@dataclass(frozen=True)
class Pair:
    landmark: str
    name: str
    """The photo's file name without its suffix."""
    photo: Path
    render: Path


def read_pairs(folder: Path) -> list[Pair]:
    """Every photo/render pair of `folder`, by landmark then name; PairsError for a wrong layout or an image that does
    not decode or does not match its photo's size (every image is decoded once here, under a second for 300 of them,
    so that a bad one is named before any teacher runs rather than minutes into the benchmark)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PairsError(f"Pairs folder {folder} {not_a_directory(folder)}; expected a folder of <landmark>/photos/ and <landmark>/renders/.")
    landmarks = [folder] if (folder / "photos").is_dir() else sorted(p for p in folder.iterdir() if (p / "photos").is_dir())
    if not landmarks:
        raise PairsError(f"Pairs folder {folder} holds no photos/ folder, nor sub-folders with one; expected <landmark>/photos/ and <landmark>/renders/.")
    pairs = [pair for landmark in landmarks for pair in _landmark_pairs(landmark)]
    if not pairs:
        raise PairsError(f"Pairs folder {folder} holds no photos (expected images with a suffix among {', '.join(IMAGE_SUFFIXES)}).")
    for pair in pairs:
        read_pair(pair)
    return pairs


def _landmark_pairs(landmark: Path) -> list[Pair]:
    renders = landmark / "renders"
    if not renders.is_dir():
        raise PairsError(f"{landmark / 'photos'} has no sibling renders/ folder; expected the renders of its photos at {renders}.")
    pairs = []
    for photo in sorted(p for p in (landmark / "photos").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
        candidates = sorted(p for p in renders.glob(f"{photo.stem}.*") if p.suffix.lower() in IMAGE_SUFFIXES)
        if not candidates:
            raise PairsError(f"Photo {photo} has no render; expected {renders / photo.stem}.<jpg|png|...> rendered at its pose.")
        pairs.append(Pair(landmark.name, photo.stem, photo, candidates[0]))
    return pairs


def read_rgb(path: Path) -> np.ndarray:
    """[H, W, 3] float32 RGB in [0, 1]; PairsError when unreadable or smaller than MIN_SIDE."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise PairsError(f"{path} could not be read as an image; expected a photo or render OpenCV reads.")
    if min(bgr.shape[:2]) < MIN_SIDE:
        raise PairsError(f"{path} is {bgr.shape[1]}x{bgr.shape[0]} pixels; expected at least {MIN_SIDE} on each side.")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def read_pair(pair: Pair) -> tuple[np.ndarray, np.ndarray]:
    """(photo, render), each [H, W, 3] float32 in [0, 1]; PairsError when their sizes differ."""
    photo, render = read_rgb(pair.photo), read_rgb(pair.render)
    if photo.shape != render.shape:
        raise PairsError(
            f"Render {pair.render} is {render.shape[1]}x{render.shape[0]} but its photo is {photo.shape[1]}x{photo.shape[0]}; "
            "expected the render made with the photo's camera, at the photo's size."
        )
    return photo, render
