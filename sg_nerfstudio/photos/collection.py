"""A folder of photos read the way COLMAP should see them: EXIF orientation applied, RGB, a capped size.

Internet photos come as JPEG or PNG of any size, portrait or landscape (often only through the EXIF
orientation tag), in colour or grey (8 or 16 bits). `prepare_photos` writes one working copy per photo into a directory
(the images SfM, training and registration then read, so the COLMAP cameras match their pixels) and fails
with one sentence on the first photo that cannot be decoded (a truncated JPEG, a file that is no image).
PIL does the decoding and the EXIF handling (`ImageOps.exif_transpose`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from PIL import Image, ImageOps

from sg_nerfstudio.errors import InputError, not_a_directory

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


class PhotoFolderError(InputError):
    """A photo folder that is missing, empty or holds a photo that cannot be decoded."""


@dataclass(frozen=True)
class PreparedPhoto:
    """One working copy: its name (the COLMAP image name), the source file and both sizes (width, height)."""

    name: str
    source: Path
    source_size: tuple[int, int]
    size: tuple[int, int]


MIN_PHOTOS = 3
"""Fewest photos a folder may hold: structure from motion needs 3 overlapping photos for a model."""


def list_photos(folder: Path) -> list[Path]:
    """The JPEG / PNG files directly inside `folder`, sorted by name; at least MIN_PHOTOS of them, else one sentence
    that names the user's folder (not a staging copy of it)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PhotoFolderError(f"Photo folder {folder} {not_a_directory(folder)}; expected a directory of JPEG or PNG photos.")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if not photos:
        raise PhotoFolderError(f"Photo folder {folder} holds no JPEG or PNG photo; expected at least {MIN_PHOTOS}.")
    if len(photos) < MIN_PHOTOS:
        raise PhotoFolderError(
            f"Photo folder {folder} holds {len(photos)} JPEG or PNG photo(s); expected at least {MIN_PHOTOS} "
            "(structure from motion needs 3 overlapping photos)."
        )
    return photos


def same_pictures(paths: list[Path]) -> str:
    """A phrase naming photos that are byte-identical copies of one another ("3 are copies of one picture: a.jpg, b.jpg,
    c.jpg"), the usual reason such a folder forms no SfM model (no baseline between them); "" when none are."""
    import hashlib

    groups: dict[str, list[str]] = {}
    for path in paths:
        groups.setdefault(hashlib.sha256(Path(path).read_bytes()).hexdigest(), []).append(Path(path).name)
    copies = sorted((names for names in groups.values() if len(names) > 1), key=len, reverse=True)
    if not copies:
        return ""
    largest = copies[0]
    shown = ", ".join(largest[:4]) + (" ..." if len(largest) > 4 else "")
    return f"{len(largest)} of them are copies of one picture ({shown})"


def files_not_read(folder: Path) -> list[str]:
    """Names of the files directly inside `folder` that `list_photos` does not take (HEIC, WebP, TIFF, RAW, notes, ...),
    sorted; hidden files (".DS_Store") left out. Reported to the user, who may want them converted to JPEG."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".") and p.suffix.lower() not in PHOTO_SUFFIXES)


def load_photo(path: Path) -> Image.Image:
    """The photo as an upright RGB PIL image (fully decoded, so a truncated file fails here)."""
    try:
        with Image.open(path) as handle:
            handle.load()
            upright = ImageOps.exif_transpose(handle)
            return as_8_bit(upright).convert("RGB")
    except Exception as error:
        raise PhotoFolderError(
            f"Photo {path} could not be decoded ({type(error).__name__}: {error}); expected a complete JPEG or PNG "
            "(remove or replace the file)."
        ) from None


SIXTEEN_BIT_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I")
"""PIL's modes of a 16-bit grey PNG (Pillow opens one as "I;16", older versions as "I")."""


def as_8_bit(image: Image.Image) -> Image.Image:
    """A 16-bit grey photo as 8-bit grey ("L", values / 257); other images as they are. PIL's own convert("RGB")
    clips 16-bit values above 255, which makes such a photo white."""
    if image.mode not in SIXTEEN_BIT_MODES:
        return image
    values = np.asarray(image, dtype=np.float64) / 257.0
    return Image.fromarray(np.clip(np.rint(values), 0, 255).astype(np.uint8), mode="L")


def capped_size(size: tuple[int, int], max_size: Optional[int]) -> tuple[int, int]:
    """(width, height) scaled down so that the long side is at most `max_size` (never up)."""
    width, height = size
    if not max_size or max(width, height) <= max_size:
        return width, height
    factor = max_size / max(width, height)
    return max(1, round(width * factor)), max(1, round(height * factor))


def prepare_photos(
    photos: list[Path], output: Path, max_size: Optional[int], on_photo: Optional[Callable[[], None]] = None,
    transform: Optional[Callable[[str, Image.Image], Image.Image]] = None,
) -> list[PreparedPhoto]:
    """Write an upright RGB copy of each photo, long side capped at `max_size`, into `output`.

    Names keep the source file name (JPEG stays JPEG at quality 95, PNG stays PNG). `transform(name, image)`
    may change each working image after resizing (e.g. the benchmark builder's in-the-wild look).
    """
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    names = [p.name for p in photos]
    if len(set(n.lower() for n in names)) != len(names):
        raise PhotoFolderError(f"Photo names must be unique regardless of case, got duplicates among {len(names)} photos.")
    prepared = []
    for path in photos:
        image = load_photo(path)
        size = capped_size(image.size, max_size)
        working = image if size == image.size else image.resize(size, Image.Resampling.LANCZOS)
        if transform is not None:
            working = transform(path.name, working)
        options = {"quality": 95} if path.suffix.lower() in (".jpg", ".jpeg") else {}
        working.save(output / path.name, **options)
        prepared.append(PreparedPhoto(path.name, path, image.size, size))
        if on_photo is not None:
            on_photo()
    return prepared
