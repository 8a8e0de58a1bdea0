"""The validation report: Table 1 (Markdown and CSV), Fig. 4 box plots (PNG), raw samples (CSV), summary (JSON).

``write_report(folder, result)`` writes

- ``table.md`` / ``table.csv``: one row per robot as in the paper's Table 1 - geometry, pixels in the
  robot's cloud (mean of the two views), position, axis orientation and tip errors (mean ± SD) and the
  processing time per pair - followed in the Markdown by the registration figures and what was run;
- ``boxplots.png``: Fig. 4-like box plots per robot of the position, axis and tip errors (median, quartiles,
  whiskers at 1.5 IQR, outliers), with the paper's reported ranges shaded;
- ``samples.csv``: every sample with its frame numbers, flags, errors, pixel counts and time;
- ``summary.json``: the run, the registration, and per robot and per posture the full statistics;
- ``calibration_registered.yaml``: when the registration was measured, the session's calibration with it
  (``metadata.ots_registration``), for the next session's ``calibration: {source: file, file: ...}``.

Statistics cover recognised samples only; lost and ambiguous samples are counted, never filled in.
"""
from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np

from appliance.validation.session import PROTOCOL_SAMPLES, Sample, ValidationResult
from appliance.validation.statistics import Summary, fraction, mean_sd_text, summarise

log = logging.getLogger(__name__)

#: The quantities summarised per robot: (sample attribute, label, unit).
QUANTITIES = (("position_mm", "position error", "mm"), ("axis_deg", "axis orientation error", "deg"),
              ("tip_mean_mm", "tip error", "mm"), ("tip_head_mm", "head tip error", "mm"),
              ("tip_tail_mm", "tail tip error", "mm"), ("pixels", "pixels in the cloud", "px"),
              ("processing_ms", "processing time", "ms"), ("truth_position_mm", "position error vs truth", "mm"),
              ("truth_axis_deg", "axis error vs truth", "deg"), ("truth_tip_mean_mm", "tip error vs truth", "mm"))
#: What the seed paper reports (Table 1, Fig. 4), drawn as a band on the box plots.
PAPER_RANGE = {"position_mm": (0.2, 0.4), "axis_deg": (1.0, 2.0)}
TABLE_COLUMNS = ("robot", "length_mm", "diameter_mm", "tip_angle_deg", "material", "pixels", "position_mm",
                 "axis_deg", "tip_mm", "processing_ms", "recognised", "ambiguous", "samples")


def _values(samples: Sequence[Sample], key: str, ok_only: bool = True) -> list[float | None]:
    return [getattr(s, key) if (s.ok or not ok_only) else None for s in samples]


def statistics(samples: Sequence[Sample]) -> dict[str, Summary]:
    """Summary of every quantity of :data:`QUANTITIES` over ``samples`` (processing time over all pairs)."""
    return {key: summarise(_values(samples, key, ok_only=key != "processing_ms")) for key, _, _ in QUANTITIES}


def _counts(samples: Sequence[Sample]) -> dict[str, Any]:
    heads = [bool(s.head_correct) for s in samples if s.ok and s.head_correct is not None]
    return {"samples": len(samples), "recognised": sum(s.ok for s in samples),
            "ambiguous": sum(s.ambiguous for s in samples), "head_identified": sum(s.head_identified for s in samples),
            "head_correct_fraction": None if not heads else round(fraction(heads), 4)}


def table_rows(result: ValidationResult) -> list[dict[str, str]]:
    """Table 1 rows (strings, as printed)."""
    rows = []
    for run in result.runs:
        stats = statistics(run.samples)
        counts = _counts(run.samples)
        robot = run.robot
        rows.append({
            "robot": str(robot.id), "length_mm": f"{robot.length_mm:g}", "diameter_mm": f"{robot.diameter_mm:g}",
            "tip_angle_deg": f"{robot.tip_angle_deg:g}", "material": ", ".join(robot.material),
            "pixels": mean_sd_text(stats["pixels"], 0), "position_mm": mean_sd_text(stats["position_mm"], 3),
            "axis_deg": mean_sd_text(stats["axis_deg"], 2), "tip_mm": mean_sd_text(stats["tip_mean_mm"], 3),
            "processing_ms": mean_sd_text(stats["processing_ms"], 1),
            "recognised": f"{counts['recognised']}/{counts['samples']}", "ambiguous": str(counts["ambiguous"]),
            "samples": str(counts["samples"])})
    return rows


def _markdown(result: ValidationResult, rows: list[dict[str, str]], summary: dict[str, Any]) -> str:
    header = ("| # | L (mm) | D (mm) | tip (deg) | material | pixels in the cloud | position error (mm) | "
              "axis error (deg) | tip error (mm) | processing (ms) | recognised | ambiguous |")
    shortfall = "" if result.plan.meets_protocol else f" (fewer than the protocol's {PROTOCOL_SAMPLES})"
    lines = ["# Validation against the optical tracker", "",
             (f"Session `{result.session}` ({'simulation' if result.simulation else 'bench'}; lab: {result.lab}), "
              f"started {result.started}, {result.wall_s:.0f} s."), "",
             (f"Run: {len(result.runs)} robot(s) x {result.plan.postures} posture(s) x {result.plan.samples} "
              f"biplane pairs per posture{shortfall}."),
             ("Errors are mean ± SD over recognised pairs against the tracker's reference mapped into the X-ray frame;"
              " pixels: mean of both views; processing: recognition of one pair on this host; ambiguous: pairs the"
              " recognition flagged (axis near an epipolar plane, axis uncertain, or the robot overlapping another"
              " structure: the reason column of samples.csv says which), included in the errors."), "",
             header, "|" + "---|" * 12]
    for r in rows:
        lines.append(f"| {r['robot']} | {r['length_mm']} | {r['diameter_mm']} | {r['tip_angle_deg']} | {r['material']} "
                     f"| {r['pixels']} | {r['position_mm']} | {r['axis_deg']} | {r['tip_mm']} | {r['processing_ms']} "
                     f"| {r['recognised']} | {r['ambiguous']} |")
    reg = summary["registration"]
    lines += ["", f"Registration X-ray -> OTS: {result.registration_source}."]
    if "fre_rms_mm" in reg:
        tre = reg.get("tre_rms_mm_at_targets") or []
        lines.append(f"FRE RMS {reg['fre_rms_mm']:.3f} mm (max {reg['fre_max_mm']:.3f}) over {reg['fiducials']} "
                     f"fiducials; FLE estimate {reg['fle_estimate_mm']:.3f} mm; expected TRE at the postures "
                     f"{np.mean(tre) if tre else math.nan:.3f} mm (Fitzpatrick); pointer pivot RMS "
                     f"{reg['pivot']['rms_mm']:.3f} mm.")
    if result.simulation:
        lines += ["", "Simulation: errors of the recognition alone, against the world's true pose:", "",
                  "| # | position (mm) | axis (deg) | tip (mm) |", "|---|---|---|---|"]
        for run in result.runs:
            stats = statistics(run.samples)
            lines.append(f"| {run.robot.id} | {mean_sd_text(stats['truth_position_mm'], 3)} | "
                         f"{mean_sd_text(stats['truth_axis_deg'], 2)} | {mean_sd_text(stats['truth_tip_mean_mm'], 3)} |")
    lines += [""] + [f"Note: {note}" for note in result.notes]
    lines += ["", "Seed paper: 0.2-0.4 mm and 1-2 deg. Box plots: boxplots.png; every sample: samples.csv.", ""]
    return "\n".join(lines)


def _boxplots(result: ValidationResult, path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("position_mm", "position error (mm)"), ("axis_deg", "axis orientation error (deg)"),
              ("tip_mean_mm", "tip error (mm)"))
    labels = [f"#{run.robot.id}" for run in result.runs]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.0), constrained_layout=True)
    for ax, (key, title) in zip(axes, panels):
        data = [[float(v) for v in _values(run.samples, key) if v is not None] for run in result.runs]
        if key in PAPER_RANGE:
            low, high = PAPER_RANGE[key]
            ax.axhspan(low, high, color="tab:green", alpha=0.12, label="paper's range")
            ax.legend(loc="upper right", fontsize=8)
        ax.boxplot([d if d else [math.nan] for d in data], showfliers=True, widths=0.6)
        ax.set_xticks(range(1, len(labels) + 1), labels)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("robot")
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"Validation against the optical tracker: {result.plan.postures} postures x "
                 f"{result.plan.samples} pairs per robot", fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _samples_csv(samples: Sequence[Sample], path: Path) -> Path:
    names = [f.name for f in fields(Sample)]
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=names + ["pixels"])
        writer.writeheader()
        for sample in samples:
            row = asdict(sample)
            for key, value in row.items():
                if isinstance(value, list):
                    row[key] = " ".join(f"{v:g}" for v in value)
                elif isinstance(value, float):
                    row[key] = f"{value:.6g}"
                elif value is None:
                    row[key] = ""
            row["pixels"] = "" if sample.pixels is None else f"{sample.pixels:g}"
            writer.writerow(row)
    return path


def summary_dict(result: ValidationResult) -> dict[str, Any]:
    targets = [c for run in result.runs for c in run.reference_centroids_mm if all(map(math.isfinite, c))]
    registration: dict[str, Any] = {"source": result.registration_source, **result.transform.to_dict()}
    if result.fiducials is not None:
        registration.update(result.fiducials.to_dict(np.array(targets) if targets else None))
    robots = []
    for run in result.runs:
        per_posture = []
        for posture, centroid in enumerate(run.reference_centroids_mm):
            chosen = [s for s in run.samples if s.posture == posture]
            known = centroid if all(map(math.isfinite, centroid)) else None
            per_posture.append({"posture": posture, "reference_centroid_mm": known, **_counts(chosen),
                                "statistics": {k: v.to_dict() for k, v in statistics(chosen).items()}})
        robot = run.robot
        robots.append({"robot": robot.id, "length_mm": robot.length_mm, "diameter_mm": robot.diameter_mm,
                       "tip_angle_deg": robot.tip_angle_deg, "material": list(robot.material),
                       **_counts(run.samples), "wall_s": round(run.wall_s, 2), "devices": run.devices,
                       "statistics": {k: v.to_dict() for k, v in statistics(run.samples).items()},
                       "postures": per_posture})
    every = statistics(result.samples)
    return {"session": result.session, "simulation": result.simulation, "lab": result.lab, "started": result.started,
            "wall_s": round(result.wall_s, 2),
            "plan": {"robots": [run.robot.id for run in result.runs], "postures": result.plan.postures,
                     "samples": result.plan.samples, "meets_protocol": result.plan.meets_protocol,
                     "protocol_samples": PROTOCOL_SAMPLES},
            "registration": registration, "robots": robots,
            "overall": {**_counts(result.samples), "statistics": {k: v.to_dict() for k, v in every.items()}},
            "paper": {"position_mm": list(PAPER_RANGE["position_mm"]), "axis_deg": list(PAPER_RANGE["axis_deg"])},
            "notes": result.notes}


def write_report(folder: str | Path, result: ValidationResult) -> dict[str, Path]:
    """Write every output file into ``folder`` (created); returns their paths by key."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    rows = table_rows(result)
    summary = summary_dict(result)
    paths = {"table_md": out / "table.md", "table_csv": out / "table.csv", "boxplots": out / "boxplots.png",
             "samples": out / "samples.csv", "summary": out / "summary.json"}
    with paths["table_csv"].open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(TABLE_COLUMNS))
        writer.writeheader()
        writer.writerows(rows)
    paths["table_md"].write_text(_markdown(result, rows, summary), encoding="utf-8")
    _boxplots(result, paths["boxplots"])
    _samples_csv(result.samples, paths["samples"])
    if result.fiducials is not None and result.calibration is not None:
        # The measured registration saved with the calibration, so the next session can reuse it.
        from appliance.registration import attach_registration
        targets = [c for run in result.runs for c in run.reference_centroids_mm if all(map(math.isfinite, c))]
        registered = attach_registration(result.calibration, result.fiducials.registration,
                                         targets=np.array(targets) if targets else None)
        paths["calibration"] = registered.save(out / "calibration_registered.yaml")
    summary["files"] = {key: str(path) for key, path in paths.items()}
    paths["summary"].write_text(json.dumps(summary, indent=2, allow_nan=False), encoding="utf-8")
    log.info("validation report written to %s", out)
    return paths
