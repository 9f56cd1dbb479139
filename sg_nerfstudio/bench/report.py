"""results.md, results.csv and robustness curves from sg-bench's run records (see runs.py).

Metrics as in the paper (section 5.1, supplement): ΔR and ΔT are averaged over the meta-images an
initialiser succeeded on; MTA is the percentage of meta-images with ΔR < 5° and ΔT < 0.2, O% those with
ΔR > 10° or ΔT > 0.5, both over the successful ones; #Failures counts meta-images without a transform.
A registration that stops with an error (e.g. nothing rendered) counts as a failure of its row.
"""

from __future__ import annotations

import csv
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

MTA_THRESHOLDS = ((3, 0.1), (7, 0.1), (10, 0.1), (5, 0.09), (5, 0.15), (5, 0.2))
OUTLIER_THRESHOLDS = ((10, 0.3), (10, 0.4), (10, 0.6), (15, 0.5), (17, 0.5), (20, 0.5))
"""The supplement's threshold sweeps (degrees, scene units)."""
CSV_COLUMNS = ("scene", "meta", "photos", "run", "family", "label", "preset", "init_failure", "refine_failure",
               "dR_before", "dT_before", "dR_after", "dT_after", "init_time_s", "refine_time_s")


def write_csv(path: Path, records: list[dict]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for r in records:
            before, after = r["before"] or {}, r["after"] or {}
            writer.writerow({
                **{k: r[k] for k in ("scene", "meta", "photos", "run", "family", "label", "init_failure", "refine_failure")},
                "preset": r.get("preset", ""),
                "dR_before": before.get("dR"), "dT_before": before.get("dT"), "dR_after": after.get("dR"), "dT_after": after.get("dT"),
                "init_time_s": round(r["init_time_s"], 2), "refine_time_s": round(r["refine_time_s"], 2),
            })


def row_metrics(errors: list[Optional[dict]]) -> dict:
    """Mean ΔR, ΔT, MTA %, O % over the successful entries (None = failure) and the failure count."""
    done = [e for e in errors if e is not None]
    if not done:
        return {"dR": None, "dT": None, "MTA": None, "O": None, "failures": len(errors), "n": len(errors)}
    return {
        "dR": statistics.mean(e["dR"] for e in done), "dT": statistics.mean(e["dT"] for e in done),
        "MTA": 100.0 * sum(e["dR"] < 5 and e["dT"] < 0.2 for e in done) / len(done),
        "O": 100.0 * sum(e["dR"] > 10 or e["dT"] > 0.5 for e in done) / len(done),
        "failures": len(errors) - len(done), "n": len(errors),
    }


def table1(records: list[dict], initialisers: tuple[str, ...]) -> list[str]:
    """The paper's Table 1: each initialiser alone, then our registration started from it (with the main preset,
    then with each `--compare-config` preset: rows "ours (<init> init, <preset>)")."""
    lines = ["| method | ΔR (°) | ΔT | MTA (%) | O (%) | #Failures |", "|---|---|---|---|---|---|"]
    for init in initialisers:
        runs = [r for r in records if r["family"] == "table1" and r["run"] == init]
        if not runs:
            continue
        baseline = row_metrics([r["before"] for r in runs])
        lines.append(_metrics_row(f"{init} (start)", baseline, f"{baseline['failures']}/{baseline['n']}"))
        for mode in _table1_modes(records, init):
            mode_runs = [r for r in records if r["family"] == "table1" and r["run"] == _table1_run(init, mode)]
            started = [r for r in mode_runs if r["before"] is not None]
            ours = row_metrics([r["after"] for r in started])
            refine_failures = sum(r["after"] is None for r in started)
            name = f"ours ({init} init)" if not mode else f"ours ({init} init, {mode})"
            lines.append(_metrics_row(name, ours, f"{refine_failures} registration errors" if refine_failures else "-"))
    return lines


def _table1_modes(records: list[dict], init: str) -> list[str]:
    """"" (the main preset), then the `--compare-config` presets the initialiser's start was also refined with."""
    return ["", *sorted({r["mode"] for r in records if r["family"] == "table1" and r.get("mode") and r["start"] == init})]


def _table1_run(init: str, mode: str) -> str:
    return f"{init}@{mode}" if mode else init


def _metrics_row(name: str, m: dict, failures: str) -> str:
    if m["dR"] is None:
        return f"| {name} | - | - | - | - | {failures} |"
    return f"| {name} | {m['dR']:.2f} | {m['dT']:.3f} | {m['MTA']:.0f} | {m['O']:.0f} | {failures} |"


def threshold_sweeps(records: list[dict], initialisers: tuple[str, ...]) -> list[str]:
    """MTA_(r, t) and O%_(r, t) over the supplement's thresholds, for each start and its refinement."""
    header = [f"MTA({r},{t})" for r, t in MTA_THRESHOLDS] + [f"O({r},{t})" for r, t in OUTLIER_THRESHOLDS]
    lines = ["| method | " + " | ".join(header) + " |", "|---|" + "---|" * len(header)]
    for init in initialisers:
        runs = [r for r in records if r["family"] == "table1" and r["run"] == init and r["before"] is not None]
        for name, key in ((f"{init} (start)", "before"), (f"ours ({init} init)", "after")):
            done = [r[key] for r in runs if r[key] is not None]
            if not done:
                continue
            mta = [100.0 * sum(e["dR"] < a and e["dT"] < b for e in done) / len(done) for a, b in MTA_THRESHOLDS]
            out = [100.0 * sum(e["dR"] > a or e["dT"] > b for e in done) / len(done) for a, b in OUTLIER_THRESHOLDS]
            lines.append(f"| {name} | " + " | ".join(f"{v:.0f}" for v in mta + out) + " |")
    return lines


def per_meta(records: list[dict], initialisers: tuple[str, ...]) -> list[str]:
    """One row per meta-image: for each start, ΔR / ΔT before -> after (or why it failed); where the scenes give them,
    first the ground truth's own residual and how far its point-based truth is from it (`BenchmarkMeta`)."""
    columns = [_table1_run(init, mode) for init in initialisers for mode in _table1_modes(records, init)]
    table1_records = [r for r in records if r["family"] == "table1"]
    truths = [key for key in ("truth_residual", "truth_disagreement") if any(r.get(key) for r in table1_records)]
    titles = {"truth_residual": "truth's residual", "truth_disagreement": "two truths differ"}
    header = [titles[key] for key in truths] + columns
    lines = ["| scene | meta-image | photos | " + " | ".join(header) + " |", "|---|---|---|" + "---|" * len(header)]
    by_meta: dict[tuple[str, str], dict[str, dict]] = defaultdict(dict)
    for r in table1_records:
        by_meta[(r["scene"], r["meta"])][r["run"]] = r
    for (scene, meta), runs in sorted(by_meta.items()):
        first = next(iter(runs.values()))
        cells = [_errors(first.get(key)) for key in truths] + [_transition(runs.get(column)) for column in columns]
        lines.append(f"| {scene} | {meta} | {first['photos']} | " + " | ".join(cells) + " |")
    return lines


def _errors(errors: Optional[dict]) -> str:
    return "-" if not errors else f"{errors['dR']:.2f}° / {errors['dT']:.3f}"


def _transition(record: Optional[dict]) -> str:
    if record is None:
        return "not run"
    if record["before"] is None:
        return "init failed"
    before = f"{record['before']['dR']:.2f}° / {record['before']['dT']:.3f}"
    if record["after"] is None:
        return f"{before} -> registration error"
    return f"{before} -> {record['after']['dR']:.2f}° / {record['after']['dT']:.3f}"


START_BANDS_DEG = ((0.0, 1.0), (1.0, 5.0), (5.0, float("inf")))
"""Bands of the start's ΔR for `start_precision_table`: the registration should end no worse than a start already within
1° and improve one between 1° and 5°."""
PRINTED_PRECISION = {"dR": 0.005, "dT": 0.0005}
"""A change smaller than what the per-meta-image table prints (0.01° / 0.001 rounded) does not count as further."""


def start_precision_table(records: list[dict], initialisers: tuple[str, ...]) -> list[str]:
    """Per initialiser start (and `--compare-config` preset) and band of the start's ΔR: how many refinements end
    further from the truth than their start, in ΔR and in ΔT, and how many of those by more than the ground truth's
    own residual (`BenchmarkMeta.truth_residual`, 0 where the scene gives none) and, where some scene gives a
    point-based truth, by more than the two truths differ (`BenchmarkMeta.truth_disagreement`, 0 where not given)."""
    allowances = ["truth_residual"] + (["truth_disagreement"] if any(r.get("truth_disagreement") for r in records) else [])
    titles = {"truth_residual": "by more than the truth's residual", "truth_disagreement": "by more than the two truths differ"}
    per_key = " | ".join(titles[a] for a in allowances)
    lines = [f"| start | start ΔR | starts | ΔR further | {per_key} | ΔT further | {per_key} |", "|---|---|---|" + "---|" * (2 + 2 * len(allowances))]
    for init in initialisers:
        for mode in _table1_modes(records, init):
            runs = [r for r in records if r["family"] == "table1" and r["run"] == _table1_run(init, mode) and r["before"] and r["after"]]
            for low, high in START_BANDS_DEG:
                band = [r for r in runs if low <= r["before"]["dR"] < high]
                if band:
                    name = init if not mode else f"{init}, {mode}"
                    counts = [" | ".join(str(sum(_further(r, key, a) for r in band)) for a in [None, *allowances]) for key in ("dR", "dT")]
                    lines.append(f"| {name} | {_band_label(low, high)} | {len(band)} | " + " | ".join(counts) + " |")
    return lines if len(lines) > 2 else []


def _further(record: dict, key: str, allowance: Optional[str]) -> bool:
    """Whether the refinement ended further than its start in `key` by more than the printed precision, plus the
    record's `allowance` ("truth_residual" or "truth_disagreement", 0 where the record has none; None: nothing)."""
    extra = (record.get(allowance) or {}).get(key, 0.0) if allowance else 0.0
    return record["after"][key] - record["before"][key] > PRINTED_PRECISION[key] + extra


def _band_label(low: float, high: float) -> str:
    return f"< {high:g}°" if low == 0 else (f"≥ {low:g}°" if high == float("inf") else f"{low:g}-{high:g}°")


def ablation_table(records: list[dict]) -> list[str]:
    rows: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        if r["family"] == "ablation":
            rows[r["label"]].append(r)
    if not rows:
        return []
    lines = ["| variant | ΔR (°) | ΔT | MTA (%) | O (%) | runs |", "|---|---|---|---|---|---|"]
    for name, runs in rows.items():
        m = row_metrics([r["after"] for r in runs])
        lines.append(_metrics_row(name, m, str(len(runs))))
    return lines


def noise_table(records: list[dict], preset: str) -> list[str]:
    """Per noise level and preset: MTA, O%, mean and median ΔR / ΔT after, the accurate runs' mean ΔR / ΔT, how often
    the dense start beside the given one won (`hypotheses.dense_start`), mean wall time (the noise runs' starts).
    Level 0 starts at the ground truth itself: where registration ends from a perfect start, the level against which
    the other starts' errors read (docs/measurements.md "Where the gap references put the truth").

    A run's preset is the one its record names (runs an earlier invocation made with another `--config` keep
    their name); records written before presets were recorded count as `preset`, this invocation's."""
    groups: dict[tuple[float, str], list[dict]] = defaultdict(list)
    for r in records:
        if r["family"] == "noise":
            groups[(float(r["label"]), r.get("mode") or r.get("preset") or preset)].append(r)
    if not groups:
        return []
    lines = [
        "| start (°, ΔT, scale) | preset | runs | MTA (%) | O (%) | ΔR (°) mean / median | ΔT mean / median | accurate: ΔR / ΔT mean | dense start won | mean s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (level, mode), runs in sorted(groups.items(), key=lambda item: (item[0][0], item[0][1] != preset, item[0][1])):
        done = [r["after"] for r in runs if r["after"] is not None]
        accurate = [e for e in done if e["dR"] < 5 and e["dT"] < 0.2]
        m = row_metrics([r["after"] for r in runs])
        digits = {"dR": 2, "dT": 3}
        mean = lambda errors, key: f"{statistics.mean(e[key] for e in errors):.{digits[key]}f}"
        both = lambda key: f"{mean(done, key)} / {statistics.median(e[key] for e in done):.{digits[key]}f}" if done else "-"
        percent = lambda key: f"{m[key]:.0f}" if m[key] is not None else "-"
        beside = [r for r in runs if r.get("other_starts") and r["after"] is not None]
        won = f"{sum(r.get('start_won') == 'dense' for r in beside)} of {len(beside)}" if beside else "-"
        seconds = statistics.mean(r["refine_time_s"] for r in runs)
        start = f"{level:g}, {level / 60:.2f}, {level:g}%" if level else "0 (the ground truth itself)"
        lines.append(
            f"| {start} | {mode} | {len(runs)} | {percent('MTA')} | {percent('O')} | {both('dR')} | {both('dT')} | "
            f"{mean(accurate, 'dR') + ' / ' + mean(accurate, 'dT') if accurate else '-'} | {won} | {seconds:.0f} |"
        )
    return lines


VERDICTS = ("registered", "uncertain", "failed")


def verdict_table(records: list[dict], preset: str = "fast-cpu") -> list[str]:
    """Confusion of the verdict (no ground truth) with the outcome by the paper's thresholds, over every run with a
    verdict (one block per preset where several were run; records written before presets were recorded count as
    `preset`, this invocation's, as in `noise_table`); and the shares the verdict is judged by."""
    preset_of = lambda r: r.get("mode") or r.get("preset") or preset
    presets = sorted({preset_of(r) for r in records if r.get("verdict") and r["after"] is not None})
    if not presets:
        return []
    several = len(presets) > 1
    lines = [("| preset " if several else "") + "| outcome (ground truth) | registered | uncertain | failed |",
             "|---|---|---|---|" + ("---|" if several else "")]
    summaries = []
    for name in presets:
        counts = _verdict_counts([r for r in records if preset_of(r) == name])
        lines += [(f"| {name} " if several else "") + f"| {outcome} | " + " | ".join(str(row[v]) for v in VERDICTS) + " |"
                  for outcome, row in counts.items()]
        summaries.append((f"{name}: " if several else "") + _verdict_shares(counts))
    return lines + [""] + summaries


def _verdict_counts(records: list[dict]) -> dict[str, dict[str, int]]:
    """outcome (accurate, in between, outlier) -> verdict -> runs."""
    counts: dict[str, dict[str, int]] = {outcome: dict.fromkeys(VERDICTS, 0) for outcome in ("accurate", "in between", "outlier")}
    for r in records:
        if r.get("verdict") and r["after"] is not None:
            e = r["after"]
            outcome = "accurate" if e["dR"] < 5 and e["dT"] < 0.2 else "outlier" if e["dR"] > 10 or e["dT"] > 0.5 else "in between"
            counts[outcome][r["verdict"]] += 1
    return counts


def _verdict_shares(counts: dict[str, dict[str, int]]) -> str:
    share = lambda hits, total: f"{100 * hits / total:.0f}% ({hits}/{total})" if total else "-"
    accurate, between, outlier = counts["accurate"], counts["in between"], counts["outlier"]
    return (f"Accurate results flagged registered: {share(accurate['registered'], sum(accurate.values()))}; "
            f"outliers flagged uncertain or failed: {share(outlier['uncertain'] + outlier['failed'], sum(outlier.values()))}; "
            f"inaccurate results flagged registered: {share(between['registered'] + outlier['registered'], sum(between.values()) + sum(outlier.values()))}.")


def robustness_curves(records: list[dict], directory: Path) -> list[str]:
    """PNG curves of the final error against the start's rotation noise and the meta-image size."""
    written = []
    for family, x_label, key, name in (
        ("noise", "initial rotation noise (°)", lambda r: float(r["label"]), "robustness_noise.png"),
        ("size", "photos in the meta-image", lambda r: int(r["label"]), "robustness_size.png"),
    ):
        groups: dict[float, list[dict]] = defaultdict(list)
        for r in records:
            if r["family"] == family and r["after"] is not None and not r.get("mode"):
                groups[key(r)].append(r["after"])
        if family == "size":  # the full meta-images, from the perturbed start
            for r in records:
                if r["family"] == "table1" and r["run"] == "perturbed" and r["after"] is not None:
                    groups[r["photos"]].append(r["after"])
        if len(groups) < 2:
            continue
        xs = sorted(groups)
        figure, axes = plt.subplots(1, 2, figsize=(9, 3.5))
        for axis, metric, label in ((axes[0], "dR", "mean ΔR (°)"), (axes[1], "dT", "mean ΔT")):
            axis.plot(xs, [statistics.mean(e[metric] for e in groups[x]) for x in xs], marker="o")
            axis.set_xlabel(x_label)
            axis.set_ylabel(label)
            axis.grid(alpha=0.3)
        figure.tight_layout()
        figure.savefig(directory / name, dpi=120)
        plt.close(figure)
        written.append(name)
    return written


def write_results(output: Path, records: list[dict], initialisers: tuple[str, ...], header: list[str], preset: str = "fast-cpu") -> Path:
    """results.csv, the PNG curves and results.md (which links them) in `output`."""
    write_csv(output / "results.csv", records)
    curves = robustness_curves(records, output)
    sections = [
        "# sg-bench results", "", *header, "",
        "## Table 1: initialisers alone and refined by our registration", "",
        "Errors averaged over the meta-images each start exists for; MTA: ΔR < 5° and ΔT < 0.2; O%: ΔR > 10° or ΔT > 0.5.", "",
        *table1(records, initialisers), "",
        "## MTA and O% over other thresholds (ΔR °, ΔT)", "", *threshold_sweeps(records, initialisers), "",
        "## Per meta-image (ΔR / ΔT before -> after)", "", *per_meta(records, initialisers), "",
    ]
    precision = start_precision_table(records, initialisers)
    if precision:
        sections += [
            "## Ended further than the start (initialiser starts)", "",
            "Changes under the printed precision (0.005°, 0.0005) do not count; the truth's residual is the RMS per-camera residual of "
            "the ground-truth alignment (gt_transform.json; 0 where the scene gives none); where a scene gives a point-based truth "
            "(gt_transform.json `point_based`: sg-make-scene --from-photos), the two truths' difference is the RMS change of the "
            "meta-image's cameras between them.", "", *precision, "",
        ]
    ablations = ablation_table(records)
    if ablations:
        sections += ["## Ablations (from the perturbed start)", "", *ablations, ""]
    noise = noise_table(records, preset)
    if noise:
        sections += ["## From noisy starts (ground truth moved by the start's rotation, translation and scale)", "", *noise, ""]
    verdicts = verdict_table(records, preset)
    if verdicts:
        sections += ["## Verdict against the ground truth (accurate: ΔR < 5° and ΔT < 0.2; outlier: ΔR > 10° or ΔT > 0.5)", "", *verdicts, ""]
    if curves:
        sections += ["## Robustness curves", "", *[f"![{name}]({name})" for name in curves], ""]
    path = output / "results.md"
    path.write_text("\n".join(sections))
    return path
