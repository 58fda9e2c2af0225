"""Result tables: Markdown (the official evaluator's metrics), JSON (everything) and CSV.

Metric keys are those of the official `result_eval.json` (`disp_epe_mean`,
`disp_temp_epe_bad_1px`, ...). delta^t_1px of the paper is `disp_temp_epe_bad_1px`.
Aggregates are frame-weighted means over sequences, as the official code computes them.
"""

from __future__ import annotations

import csv
import json
import os
import pathlib

from sav_jax._checks import plural

# (column heading, metric key); bad rates and delta^t in percent.
COLUMNS = (
    ("EPE", "disp_epe_mean"), ("bad-0.5 %", "disp_epe_bad_0.5px"),
    ("bad-1 %", "disp_epe_bad_1px"), ("bad-2 %", "disp_epe_bad_2px"),
    ("bad-3 %", "disp_epe_bad_3px"), ("TEPE", "disp_temp_epe_mean"),
    ("δt-0.5px %", "disp_temp_epe_bad_0.5px"), ("δt-1px %", "disp_temp_epe_bad_1px"),
    ("δt-2px %", "disp_temp_epe_bad_2px"), ("δt-3px %", "disp_temp_epe_bad_3px"),
    ("TCC", "disp_TCC"), ("TCM", "disp_TCM"), ("OPW", "disp_OPW"), ("RTC", "disp_RTC"),
)
HIGHER_IS_BETTER = ("disp_TCC", "disp_TCM", "disp_RTC")
ALL = "ALL (frame-weighted)"


def _columns(rows: list[dict]) -> list[tuple[str, str]]:
  """The COLUMNS present in at least one row."""
  return [(h, k) for h, k in COLUMNS if any(k in r for r in rows)]


def _fmt(v) -> str:
  return "–" if v is None else f"{v:.3f}"


def _read_from(sources: list[str]) -> str | None:
  """The folder the sequences' frames were read from: their common folder, or a few of them
  where that is only a filesystem root (or none: folders on other drives); None without any."""
  if not sources:
    return None
  try:
    common = os.path.commonpath(sources)
  except ValueError:  # on other drives (Windows), or relative beside absolute
    common = None
  if common and os.path.dirname(common) != common:
    return common
  from sav_jax.data.base import some_of  # pylint: disable=import-outside-toplevel
  return some_of(sorted(set(sources)), most=3)


def _with_gt(summary: dict) -> str:
  """" (F with ground truth)" where the aggregates weigh fewer frames than were predicted."""
  measured = max((_measured(summary, m) for m in summary["methods"].values()), default=0)
  if 0 < measured < summary["frames"]:
    return f" ({measured} with ground truth)"
  return ""


def markdown(summary: dict) -> str:
  """The Markdown report of `build_summary`'s dictionary."""
  methods = summary["methods"]
  cols = _columns([m["aggregate"] for m in methods.values()])
  higher = [h for h, k in cols if k in HIGHER_IS_BETTER]
  lines = [f"# {summary['dataset']} ({summary['split']})", "",
           f"Weights: {summary['weights']}  ",
           f"iters {summary['config']['iters']}, window {summary['config']['window']} / stride "
           f"{summary['config']['stride']}, {summary['config']['dtype']}; "
           f"{plural(len(summary['sequences']), 'sequence')}, {summary['frames']} frames"
           + _with_gt(summary) + "."]
  read_from = _read_from([seq["source"] for seq in summary["sequences"] if seq.get("source")])
  if read_from:  # Sintel's "test" split is its training/ folder, e.g.: where the frames came from
    lines[-1] += "  "
    lines.append(f"Frames read from {read_from}")
  lines += ["", "## Aggregate (frame-weighted mean over sequences; lower is better"
            + (f", except {', '.join(higher)})" if higher else ")"), ""]
  head = ["Method"] + [h for h, _ in cols] + ["frames/s"]
  lines += ["| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
  for m in methods.values():
    vals = [_fmt(m["aggregate"].get(k)) for _, k in cols]
    lines.append("| " + " | ".join([m["name"], *vals, f"{m['frames_per_second']:.2f}"]) + " |")
  if not cols:
    lines += ["", "No ground truth in this dataset: no metrics (predictions and plots only)."]
  lines += ["", "## Per sequence", ""]
  head = ["Sequence", "Frames", "Method"] + [h for h, _ in cols]
  lines += ["| " + " | ".join(head) + " |", "|---|---:|---" + "|---:" * len(cols) + "|"]
  for seq in summary["sequences"]:
    for key in seq["metrics"] or seq.get("seconds", {}):  # without GT: the rows, no values
      res = seq["metrics"].get(key, {})
      vals = [_fmt(res.get(k)) for _, k in cols]
      lines.append("| " + " | ".join([seq["name"], str(seq["frames"]), methods[key]["name"],
                                      *vals]) + " |")
  notes = [n for seq in summary["sequences"] for n in seq.get("notes", [])]
  skipped = summary.get("skipped_sequences") or []
  if skipped:  # as the official evaluation skips them: the table covers the others
    notes.append(f"{plural(len(skipped), 'sequence')} shorter than "
                 f"sample_len={summary['config']['sample_len']} frames skipped, as the "
                 f"official evaluation does: {', '.join(skipped)}.")
  if notes:
    lines += ["", "Notes:", *(f"- {n}" for n in notes)]
  compiled = ", ".join(f"{m['name']} {m['compile_seconds']:.1f} s"
                       for m in methods.values() if m.get("compile_seconds"))
  lines += ["", "EPE/TEPE in px with the official denominators (non-zero errors); bad-N and "
            "δt-N px: % of those pixels above N px. δt-1px is the paper's δ^t_1px. frames/s: "
            "prediction time without compilation"
            + (f" (compilation: {compiled})." if compiled else ".")
            + (f" Metrics: {summary['metrics_seconds']:.1f} s"
               + (" (RAFT's flows included)." if summary["config"]["metrics"].get("raft") else ".")
               if "metrics_seconds" in summary else ""), ""]
  return "\n".join(lines)


def _measured(summary: dict, method: dict) -> int:
  """The frames `method`'s aggregate weighs (results.json of runs before the field: all)."""
  return method.get("measured_frames", summary["frames"])


# How results.md and results.csv show the bytes of a path or sequence name that is not UTF-8
# (Latin-1 from a zip made on Windows, kept by Python as surrogates): as `\udce9` (writing
# them failed with "surrogates not allowed" after the whole run; results.json keeps them,
# escaped as JSON does; the printed lines show them so too: `tools.printable_names`).
NOT_UTF8 = "backslashreplace"


def write_csv(path, summary: dict) -> None:
  """One row per (method, sequence) plus one aggregate row per method, whose frames are those
  its mean weighs (the sequences with ground truth)."""
  rows = []
  for seq in summary["sequences"]:
    for key, res in seq["metrics"].items():
      rows.append({"method": key, "sequence": seq["name"], "frames": seq["frames"], **res})
  for key, m in summary["methods"].items():
    rows.append({"method": key, "sequence": ALL, "frames": _measured(summary, m),
                 **m["aggregate"]})
  keys = [k for _, k in COLUMNS if any(k in r for r in rows)]
  keys += sorted({k for r in rows for k in r} - set(keys) - {"method", "sequence", "frames"})
  with open(path, "w", newline="", encoding="utf-8", errors=NOT_UTF8) as fh:
    writer = csv.DictWriter(fh, ["method", "sequence", "frames"] + keys)
    writer.writeheader()
    writer.writerows(rows)


def write_all(out: pathlib.Path, summary: dict) -> list[pathlib.Path]:
  """Writes results.json, results.csv and results.md; returns their paths."""
  out.mkdir(parents=True, exist_ok=True)
  paths = [out / "results.json", out / "results.csv", out / "results.md"]
  paths[0].write_text(json.dumps(summary, indent=1), encoding="utf-8")
  write_csv(paths[1], summary)
  paths[2].write_text(markdown(summary), encoding="utf-8", errors=NOT_UTF8)
  return paths
