"""Evaluation plots drawn with OpenCV (no matplotlib needed).

`write_curves`: per-frame EPE and per-frame-pair TEPE of each method, two panels.
`write_strip`: a grid of a few frames (columns) x left image / ground truth / each
method (rows), with one colour range for the whole grid (from the ground truth), and under
each method its error against the ground truth in KITTI's error colours
(`viz.colorize_error`: blues up to the 3 px / 5% outlier threshold, oranges to red above).
"""

from __future__ import annotations

import pathlib

import cv2
import numpy as np

from sav_jax import viz

# BGR line colours, one per method in order.
_COLOURS = ((200, 90, 30), (40, 40, 220), (40, 160, 40), (160, 40, 160), (0, 140, 220))
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_PANEL = (760, 300)  # width, height of one curve panel
_MARGIN = (70, 20, 36, 44)  # left, right, top, bottom


def _drawable(text: str) -> str:
  """`text` with `?` for the characters of a name that is not UTF-8 (a sequence folder from a
  zip made on Windows, kept by Python as surrogates): OpenCV's putText and getTextSize crashed
  the process with a segmentation fault on them."""
  return text.encode("utf-8", "replace").decode("utf-8")


def _text(img, text, org, scale=0.45, colour=(0, 0, 0), thickness=1):
  cv2.putText(img, _drawable(text), (int(org[0]), int(org[1])), _FONT, scale, colour, thickness,
              cv2.LINE_AA)


def _panel(series: dict[str, np.ndarray], title: str, xlabel: str) -> np.ndarray:
  """One line chart `[H, W, 3]` (BGR) of `label -> values` over their index."""
  w, h = _PANEL
  left, right, top, bottom = _MARGIN
  img = np.full((h, w, 3), 255, np.uint8)
  pw, ph = w - left - right, h - top - bottom
  vals = [np.asarray(v, np.float64) for v in series.values() if len(v)]
  finite = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.zeros(0)
  ystep = viz.nice_step(float(finite.max()) if finite.size else 0.0, 5)
  ymax = ystep * max(1, int(np.ceil(finite.max() / ystep - 1e-9))) if finite.size else ystep
  n = max((len(v) for v in vals), default=1)
  xmax = max(n - 1, 1)
  to_px = lambda i, y: (left + pw * i / xmax, top + ph * (1 - min(y, ymax) / ymax))  # noqa: E731
  for k in range(int(round(ymax / ystep)) + 1):  # horizontal grid and y ticks
    y = ystep * k
    py = int(round(to_px(0, y)[1]))
    cv2.line(img, (left, py), (left + pw, py), (225, 225, 225), 1)
    _text(img, f"{y:.3g}", (4, py + 4), 0.4)
  for i in range(0, xmax + 1, max(1, int(viz.nice_step(xmax, 10)))):
    px = int(round(to_px(i, 0)[0]))
    cv2.line(img, (px, top + ph), (px, top + ph + 4), (0, 0, 0), 1)
    _text(img, str(i), (px - 6, top + ph + 18), 0.4)
  cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
  for c, (label, v) in enumerate(series.items()):
    colour = _COLOURS[c % len(_COLOURS)]
    v = np.asarray(v, np.float64)
    ok = np.isfinite(v)  # NaN (a frame without valid GT): a gap in the line, no point
    pts = np.array([to_px(i, y) for i, y in enumerate(np.where(ok, v, 0.0))],
                   np.float64).round().astype(np.int32).reshape(-1, 2)
    runs = np.split(np.arange(len(v)), np.flatnonzero(np.diff(ok.astype(np.int8))) + 1)
    lines = [pts[r].reshape(-1, 1, 2) for r in runs if len(r) > 1 and ok[r[0]]]
    if lines:
      cv2.polylines(img, lines, False, colour, 2, cv2.LINE_AA)
    alone = [r[0] for r in runs if len(r) == 1 and ok[r[0]]]  # no line shows these
    for p in pts[np.flatnonzero(ok)] if len(pts) <= 60 else pts[alone]:
      cv2.circle(img, tuple(int(q) for q in p), 3, colour, -1, cv2.LINE_AA)
    ly = top + 16 + 18 * c
    cv2.line(img, (left + pw - 190, ly - 4), (left + pw - 165, ly - 4), colour, 2)
    _text(img, label, (left + pw - 158, ly))
  _text(img, title, (left, top - 12), 0.55)
  _text(img, xlabel, (left + pw // 2 - 40, h - 8), 0.45)
  return img


def write_curves(path, curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str = ""
                 ) -> pathlib.Path:
  """Writes per-frame EPE and TEPE curves of each method as a PNG.

  Args:
    path: output `.png`.
    curves: method label -> (EPE per frame `[T]`, TEPE per frame pair `[T-1]`) in px.
    title: heading (e.g. the sequence name).

  Returns:
    The path written.
  """
  epe = _panel({k: v[0] for k, v in curves.items()}, f"{title}  EPE per frame (px)", "frame")
  tepe = _panel({k: v[1] for k, v in curves.items()}, f"{title}  TEPE per frame pair (px)",
                "frame t (pair t, t+1)")
  _write_png(path, np.concatenate([epe, tepe], axis=0))
  return pathlib.Path(path)


def _write_png(path, bgr: np.ndarray) -> None:
  """Writes a BGR image as a PNG at `path`, a path of any bytes (OpenCV's imwrite crashed the
  process with a segmentation fault on a name that is not UTF-8: encoded here, written by
  Python, as `viz.write_png16` does)."""
  encoded, data = cv2.imencode(".png", bgr)
  if not encoded:
    raise OSError(f"{path}: OpenCV could not encode the PNG")
  with open(path, "wb") as fh:
    fh.write(data.tobytes())


def _tile(img: np.ndarray, size: int) -> np.ndarray:
  h, w = img.shape[:2]
  s = min(1.0, size / max(h, w))
  if s < 1.0:
    img = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))),
                     interpolation=cv2.INTER_AREA)
  return img


def write_strip(path, clip: dict, preds: dict[str, np.ndarray], frames: int = 6,
                tile: int = 320) -> pathlib.Path:
  """Writes a grid of colourized disparities (rows) for a few frames (columns).

  Args:
    path: output `.png`.
    clip: `left [T, H, W, 3]` uint8 RGB, `disparity`/`valid` `[T, H, W]` or None.
    preds: method label -> `[T, H, W]` disparity.
    frames: number of columns (frames evenly spread over the sequence).
    tile: longest side of each tile (px).

  Returns:
    The path written.
  """
  t = len(clip["left"])
  idx = np.unique(np.linspace(0, t - 1, max(1, min(frames, t))).round().astype(int))
  gt, valid = clip.get("disparity"), clip.get("valid")
  # the ground truth's range, or the first prediction's where the shown frames have no
  # usable ground-truth pixel (fully occluded / invalid frames; no ground truth at all)
  shown = np.abs(gt[idx]) if gt is not None else None
  if shown is not None and np.any(np.isfinite(shown) & (shown > 0) & (valid[idx] > 0.5)):
    vmin, vmax = viz.disparity_range(shown, valid[idx], percentiles=(1.0, 99.0))
  else:
    vmin, vmax = viz.disparity_range(next(iter(preds.values()))[idx], percentiles=(1.0, 99.0))
  rows = [("left", [clip["left"][i] for i in idx])]
  if gt is not None:
    rows.append(("ground truth", [viz.colorize(np.abs(gt[i]), vmin, vmax, valid=valid[i])
                                  for i in idx]))
  for label, p in preds.items():
    rows.append((label, [viz.colorize(p[i], vmin, vmax) for i in idx]))
    if gt is not None:  # KITTI's error colours against |gt| (the evaluator's abs())
      rows.append((f"{label} error", [viz.colorize_error(p[i], np.abs(gt[i]), valid[i])
                                      for i in idx]))
  # wide enough for the longest label ("Stereo Any Video error" at 0.5: ~190 px)
  label_w = max(150, 12 + max(cv2.getTextSize(_drawable(label), _FONT, 0.5, 1)[0][0]
                              for label, _ in rows))
  lines = []
  for label, images in rows:
    tiles = [_tile(im, tile) for im in images]
    row = np.concatenate(tiles, axis=1)[..., ::-1]  # RGB -> BGR
    head = np.full((row.shape[0], label_w, 3), 255, np.uint8)
    _text(head, label, (6, row.shape[0] // 2 + 5), 0.5)
    lines.append(np.concatenate([head, row], axis=1))
  header = np.full((24, lines[0].shape[1], 3), 255, np.uint8)
  _text(header, f"frames {', '.join(map(str, idx))}; colour range {vmin:.2f}..{vmax:.2f} px",
        (6, 17), 0.45)
  _write_png(path, np.concatenate([header] + lines, axis=0))
  return pathlib.Path(path)
