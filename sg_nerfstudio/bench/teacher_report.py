"""What `sg-bench teacher` writes: the summary per teacher (overall and per landmark), teacher-benchmark.json,
teacher-benchmark.md (the tables the console shows) and landscapes.png (the shift landscapes of a few pairs).
The measures are defined in bench/teacher.py."""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from rich.table import Table  # noqa: E402

from sg_nerfstudio.bench.teacher import BASIN_DISTANCES, SIFT_ENOUGH, Landscapes  # noqa: E402

OVERALL = "all"
COLUMNS = (
    ("pairs", "teacher (pairs)"), ("identifiable", "identifiable %"), ("basin_2", "basin@2 %"), ("basin_4", "basin@4 %"),
    ("basin_6", "basin@6 %"), ("prominence", "prominence"), ("rotation_identifiable", "roll id. %"),
    ("zoom_identifiable", "zoom id. %"), ("control_identifiable", "unrelated id. %"), ("seconds_per_pair", "s / pair"),
)


def _percent(values: list) -> float | None:
    return round(100.0 * float(np.mean(values)), 1) if values else None


def summarise_teacher(records: list[dict], name: str) -> dict:
    """The measures of teacher `name` over `records` (one per pair): shares in percent, the median prominence."""
    measures = [r["teachers"][name] for r in records]
    row = {
        "pairs": len(records),
        "identifiable": _percent([m["identifiable"] for m in measures]),
        **{f"basin_{k}": _percent([m["basin"][str(k)] for m in measures]) for k in BASIN_DISTANCES},
        "prominence": round(statistics.median(m["prominence"] for m in measures), 3),
        "control_identifiable": _percent([m["control_identifiable"] for m in measures if "control_identifiable" in m]),
        "control_pairs": sum("control_identifiable" in m for m in measures),
        "seconds_per_pair": round(float(np.mean([r["seconds"][name] for r in records])), 2),
    }
    for key in ("rotation_identifiable", "rotation_basin", "zoom_identifiable", "zoom_basin"):
        row[key] = _percent([m[key] for m in measures])
    return row


def summarise(records: list[dict]) -> dict:
    """{"teachers": {name: {landmark or OVERALL: row}}, "sift": {landmark or OVERALL: {...}}}."""
    names = list(records[0]["teachers"])
    groups = {OVERALL: records}
    for record in records:
        groups.setdefault(record["landmark"], []).append(record)
    return {
        "teachers": {name: {group: summarise_teacher(members, name) for group, members in groups.items()} for name in names},
        "sift": {group: {"pairs": len(members), f"share_with_{SIFT_ENOUGH}": _percent([r["sift_matches"] >= SIFT_ENOUGH for r in members]),
                         "median_matches": statistics.median(r["sift_matches"] for r in members)} for group, members in groups.items()},
    }


@dataclass
class Tabled:
    """A table as plain strings, shown by rich on the console and written as Markdown."""

    title: str
    headers: list[str]
    rows: list[list[str]]

    def rich(self) -> Table:
        table = Table(title=self.title)
        for header in self.headers:
            table.add_column(header, justify="right")
        for row in self.rows:
            table.add_row(*row)
        return table

    def markdown(self) -> str:
        lines = [self.title, "", "| " + " | ".join(self.headers) + " |", "|" + "---|" * len(self.headers)]
        return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in self.rows]) + "\n"


def overall_table(summary: dict) -> Tabled:
    """One row per teacher, over all pairs."""
    rows = [[f"{name} ({groups[OVERALL]['pairs']})" if key == "pairs" else str(groups[OVERALL][key]) for key, _ in COLUMNS]
            for name, groups in summary["teachers"].items()]
    title = "Teachers over all pairs (shifts up to 6 cells = 19% of the width, rolls up to 10°, zooms up to 15%)"
    return Tabled(title, [header for _, header in COLUMNS], rows)


def landmark_table(summary: dict) -> Tabled:
    """Per landmark: SIFT's availability and each teacher's identifiable % / basin@4 %."""
    names = list(summary["teachers"])
    rows = []
    for group, sift in summary["sift"].items():
        cells = [f"{summary['teachers'][n][group]['identifiable']} / {summary['teachers'][n][group]['basin_4']}" for n in names]
        rows.append([group, str(sift["pairs"]), str(sift[f"share_with_{SIFT_ENOUGH}"]), f"{sift['median_matches']:g}", *cells])
    title = f"Per landmark: pairs with {SIFT_ENOUGH}+ right SIFT matches, and each teacher's identifiable % / basin@4 %"
    return Tabled(title, ["landmark", "pairs", f"SIFT {SIFT_ENOUGH}+ %", "SIFT median", *names], rows)


def landscape_figure(path: Path, shown: list[tuple[str, np.ndarray, np.ndarray, dict[str, Landscapes]]]) -> None:
    """Photo, render and each teacher's shift landscape (darker = closer; + the truth, x the lowest point) for each
    (title, photo, render, landscapes by teacher) in `shown`."""
    names = list(shown[0][3])
    figure, axes = plt.subplots(2 + len(names), len(shown), figsize=(2.2 * len(shown), 2.2 * (2 + len(names))), squeeze=False)
    for column, (title, photo, render, found) in enumerate(shown):
        axes[0, column].imshow(photo)
        axes[0, column].set_title(title, fontsize=8)
        axes[1, column].imshow(render)
        for row, name in enumerate(names, start=2):
            shift = found[name].shift
            axes[row, column].imshow(shift, cmap="viridis")
            centre = shift.shape[0] // 2
            lowest = np.unravel_index(int(np.argmin(shift)), shift.shape)
            axes[row, column].plot([centre], [centre], "w+", markersize=10)
            axes[row, column].plot([lowest[1]], [lowest[0]], "rx", markersize=8)
    for row, label in enumerate(["photo", "render", *names]):
        axes[row, 0].set_ylabel(label, fontsize=9)
    for axis in axes.flat:
        axis.set_xticks([])
        axis.set_yticks([])
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def write_report(directory: Path, records: list[dict], summary: dict, header: str) -> list[Table]:
    """teacher-benchmark.json and teacher-benchmark.md in `directory`; returns the tables for the console."""
    tables = [overall_table(summary), landmark_table(summary)]
    (directory / "teacher-benchmark.json").write_text(json.dumps({"header": header, "summary": summary, "pairs": records}, indent=1))
    (directory / "teacher-benchmark.md").write_text(header + "\n\n" + "\n".join(t.markdown() for t in tables))
    return [t.rich() for t in tables]
