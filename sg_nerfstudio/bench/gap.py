"""How wide a scene's photo/reference gap is, beside the paper's: the teacher benchmark's measures at the true pose.

A gap scene's reference is a render of a lower-fidelity model, as the paper's references are splats trained on Google
Earth Studio renders. Whether its gap is as wide as the paper's is measured on the scene's own photo/render pairs
(each photo and the reference rendered at its true pose; layout: bench/pairs.py) with the two figures that decide what
works there: the share of photos with SIFT_ENOUGH right SIFT matches (what the SIFT initialisers and keypoint anchors
need) and the CPU default teacher's identifiability (bench/teacher.py's measure). PAPER_PAIRS holds the same figures on
the paper's own 147 pairs; photos are in the paper's range when SIFT works on at most SIFT_SHARE_LIMIT of them and
the identifiability is at most IDENTIFIABLE_MARGIN above the paper's. Like the paper's figures, that verdict is for a
set of landmarks (a suite, its photos pooled: `pool`); single landmarks spread widely (PAPER_LANDMARK_RANGE).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
from PIL import Image as PILImage
from rich.progress import Progress

from sg_nerfstudio.bench.pairs import MIN_SIDE, read_pairs, read_pair
from sg_nerfstudio.bench.teacher import SIFT_ENOUGH, build_describers, identifiable, landscapes, sift_matches

GAP_TEACHER = "offline"
"""The teacher whose identifiability is measured: sg-feature-splat-cpu's (a test keeps the two the same)."""
PAPER_PAIRS = {"pairs": 147, "sift_share": 9 / 147, "identifiable": 130 / 147}
"""The paper's photo/render pairs (../shared/domain-gap, 11 WikiEarth landmarks), measured by
`sg-bench teacher ../shared/domain-gap --output OUT --teachers offline` (docs/teacher-benchmark.md): SIFT finds 15+
right matches on 9 of 147 photos, `offline` identifies 130."""
PAPER_LANDMARK_RANGE = {"sift_share": (0.0, 7 / 31), "identifiable": (10 / 17, 1.0)}
"""Lowest and highest per-landmark figure on the paper's pairs (same run): identifiable from 10 of 17 photos (landmark 85)
to all (7 of the 11 landmarks); SIFT from none (9 landmarks) to 7 of 31 photos (landmark 20)."""
SIFT_SHARE_LIMIT = 0.15
IDENTIFIABLE_MARGIN = 0.05


def measure_gap(pairs_folder: Path, progress: Optional[Progress] = None) -> dict:
    """The gap measures of the photo/render pairs in `pairs_folder` (bench/pairs.py's layout): summary (`summarise`)
    plus "per_pair" [{"pair", "sift_matches", "identifiable"}]; pairs smaller than the benchmark's MIN_SIDE are not
    measured ({"measured": False, "why": ...})."""
    pairs = read_pairs(pairs_folder) if _large_enough(pairs_folder) else []
    if not pairs:
        return {"measured": False, "why": f"photos smaller than {MIN_SIDE} pixels are too small for the measure"}
    describe = build_describers((GAP_TEACHER,))[GAP_TEACHER]
    task = progress.add_task("measuring the photo/reference gap", total=len(pairs)) if progress is not None else None
    per_pair = []
    for pair in pairs:
        photo, render = read_pair(pair)
        per_pair.append({
            "pair": f"{pair.landmark}/{pair.name}", "sift_matches": sift_matches(photo, render),
            "identifiable": identifiable(landscapes(describe, photo, render, shift_only=True).shift),
        })
        if progress is not None:
            progress.advance(task)
    return summarise(per_pair)


def summarise(per_pair: list[dict]) -> dict:
    """{"measured", "pairs", "teacher", "sift_share", "sift_median", "identifiable", "in_paper_range", "per_pair"}."""
    sift = np.asarray([p["sift_matches"] for p in per_pair])
    measures = {
        "measured": True, "pairs": len(per_pair), "teacher": GAP_TEACHER, "sift_share": float(np.mean(sift >= SIFT_ENOUGH)),
        "sift_median": float(np.median(sift)), "identifiable": float(np.mean([p["identifiable"] for p in per_pair])),
    }
    return {**measures, "in_paper_range": in_paper_range(measures), "per_pair": per_pair}


def pool(scenes: dict[str, dict]) -> dict:
    """The measures of several scenes' pairs together (scene name -> measure_gap's record); unmeasured scenes are
    left out, and so is everything when none was measured."""
    per_pair = [{**p, "pair": f"{name}/{p['pair']}"} for name, m in scenes.items() if m.get("measured") for p in m["per_pair"]]
    return summarise(per_pair) if per_pair else {"measured": False, "why": "no scene's photos were measured"}


def benchmark_gap(scenes: Iterable) -> dict:
    """`pool` of the gaps that `sg-make-scene` measured for these scenes (bench.layout.BenchmarkScene: their
    scene.json "gap"); scenes without a measured gap (filtered-photo references, older scenes) are left out."""
    measured = {}
    for scene in scenes:
        try:
            gap = json.loads((Path(scene.directory) / "scene.json").read_text()).get("gap") or {}
        except (OSError, ValueError, AttributeError):
            continue
        if gap.get("measured"):
            measured[scene.name] = gap
    return pool(measured)


def in_paper_range(measures: dict) -> bool:
    return measures["sift_share"] <= SIFT_SHARE_LIMIT and measures["identifiable"] <= PAPER_PAIRS["identifiable"] + IDENTIFIABLE_MARGIN


def gap_sentence(measures: dict) -> str:
    """One line for the builder's output: the scene's gap beside the paper's."""
    if not measures.get("measured"):
        return f"photo/reference gap not measured: {measures['why']}."
    verdict = "in the paper's range" if measures["in_paper_range"] else "NOT in the paper's range"
    low, high = (100 * v for v in PAPER_LANDMARK_RANGE["identifiable"])
    return (
        f"photo/reference gap at the true pose ({measures['pairs']} photos): SIFT {SIFT_ENOUGH}+ right matches on "
        f"{100 * measures['sift_share']:.1f}% of photos (median {measures['sift_median']:.0f}), {measures['teacher']} "
        f"identifies {100 * measures['identifiable']:.1f}%; the paper's pairs: {100 * PAPER_PAIRS['sift_share']:.1f}% and "
        f"{100 * PAPER_PAIRS['identifiable']:.1f}%, {low:.0f}-{high:.0f}% by landmark ({verdict}: SIFT <= "
        f"{100 * SIFT_SHARE_LIMIT:.0f}%, identifiable <= {100 * (PAPER_PAIRS['identifiable'] + IDENTIFIABLE_MARGIN):.1f}%)."
    )


def _large_enough(folder: Path) -> bool:
    """Whether every photo in the pairs folder has both sides >= MIN_SIDE (from the file headers; read_pairs decodes)."""
    photos = sorted([*Path(folder).glob("photos/*"), *Path(folder).glob("*/photos/*")])
    return bool(photos) and all(min(_header_size(path)) >= MIN_SIDE for path in photos)


def _header_size(path: Path) -> tuple[int, int]:
    with PILImage.open(path) as image:
        return image.size
