"""On-disk cache of teacher feature maps, keyed by image content and extractor settings.

One file per (image, settings): `<cache dir>/<sha256>.pt` holding the map as float16 plus the key it was
stored under. A changed image or setting gives another key (recomputed); an unreadable or mismatching
file is recomputed with a warning, never trusted. Writes are atomic (temporary file + rename).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from torch import Tensor

from nerfstudio.utils.rich_utils import CONSOLE


def default_cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "sg_nerfstudio" / "features"


def cache_key(image: Tensor, settings: dict) -> str:
    """sha256 over the image bytes, its shape and dtype, and the extractor settings."""
    digest = hashlib.sha256()
    array = image.detach().cpu().contiguous()
    digest.update(json.dumps({"shape": list(array.shape), "dtype": str(array.dtype), "settings": settings}, sort_keys=True).encode())
    digest.update(array.numpy().tobytes())
    return digest.hexdigest()


class FeatureCache:
    def __init__(self, directory: Optional[Path] = None):
        self.directory = Path(directory) if directory is not None else default_cache_dir()

    def path(self, key: str) -> Path:
        return self.directory / f"{key}.pt"

    def load(self, key: str) -> Optional[Tensor]:
        """The cached map, or None when absent or untrustworthy (warned)."""
        path = self.path(key)
        if not path.exists():
            return None
        try:
            record = torch.load(path, map_location="cpu", weights_only=True)
            features = record["features"]
            if record.get("key") != key or not isinstance(features, Tensor) or features.dim() != 3 or not torch.isfinite(features).all():
                raise ValueError("content does not match its key")
        except Exception as error:
            CONSOLE.print(f"[yellow]Ignoring corrupt feature cache file {path} ({error}); recomputing.[/yellow]")
            return None
        return features.float()

    def store(self, key: str, features: Tensor) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=self.directory, prefix=f".{key}.", suffix=".tmp")
        os.close(handle)
        try:
            torch.save({"key": key, "features": features.half()}, temporary)
            os.replace(temporary, self.path(key))
        finally:
            if os.path.exists(temporary):
                os.remove(temporary)


def extract_all(
    images: Sequence[Tensor] | Callable[[int], Tensor],
    count: int,
    teacher,
    cache: FeatureCache,
    description: str,
) -> list[Tensor]:
    """Teacher features for `count` images (cached), with a rich progress bar.

    Args:
        images: a sequence of [H, W, 3] images (uint8 or float in [0, 1]) or a function index -> image.
        count: number of images.

    Returns:
        one [rows, columns, D] float32 map per image.
    """
    get = images if callable(images) else images.__getitem__
    settings = teacher.settings()
    results: list[Tensor] = []
    computed = 0
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=CONSOLE, transient=True) as progress:
        task = progress.add_task(description, total=count)
        for index in range(count):
            image = get(index)
            key = cache_key(image, settings)
            features = cache.load(key)
            if features is None:
                as_float = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
                features = teacher.extract(as_float[..., :3])
                cache.store(key, features)
                features = features.half().float()  # exactly what a later cache hit returns
                computed += 1
            results.append(features)
            progress.advance(task)
    CONSOLE.print(f"{description}: {count} maps ({count - computed} from cache {cache.directory}, {computed} computed).")
    return results
