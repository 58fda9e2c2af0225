"""Exact ray casting of textured planar layers for the synthetic stereo generator.

A layer is a plane in left-camera coordinates (metres) carrying a periodic RGBA
texture and, for objects, a shape in the plane's texel coordinates. `render_view`
intersects every pixel's ray with every layer (exact per-pixel depth, also for
slanted planes), keeps the nearest hit in a z-buffer and samples the texture
bilinearly; `valid_mask` marks left pixels whose 3D point is visible in the right
view, testing occlusion analytically rather than on the right pixel grid.
`sav_jax.data.synthetic` builds the layers (scene sampling, motion) and calls these.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np


class Camera(NamedTuple):
  """Rectified pinhole pair: focal (px), principal point (px), baseline (m)."""

  fx: float
  cx: float
  cy: float
  baseline: float


class Layer(NamedTuple):
  """One planar layer at one frame (all vectors in left-camera coordinates, metres).

  `e1`, `e2` are the in-plane axes scaled to texels per metre, so `(X - center) . e1`
  is a texel offset from the layer's centre; `origin` is the centre's texel position.
  """

  center: np.ndarray  # [3]
  normal: np.ndarray  # [3] unit
  e1: np.ndarray  # [3]
  e2: np.ndarray  # [3]
  kind: str  # "background" or one of synthetic.SHAPES
  params: tuple  # shape parameters in texels
  extent: tuple  # (umin, umax, vmin, vmax) texel box holding the shape (() for background)
  zmin: float  # lower bound of the layer's depth where it can be seen (m)
  texture: np.ndarray  # [S, S, 4] uint8 RGBA, periodic
  origin: tuple[float, float]  # texel coordinate of `center`


def unit(v: np.ndarray) -> np.ndarray:
  """v scaled to unit length."""
  return v / np.linalg.norm(v)


def plane_axes(normal: np.ndarray, theta: float) -> tuple[np.ndarray, np.ndarray]:
  """Orthonormal in-plane axes, rotated by theta about the normal."""
  b1 = unit(np.array([1.0, 0.0, 0.0]) - normal[0] * normal)
  b2 = np.cross(normal, b1)
  c, s = math.cos(theta), math.sin(theta)
  return c * b1 + s * b2, -s * b1 + c * b2


def cast(layer: Layer, ox: float, rx: np.ndarray, ry: np.ndarray):
  """Intersects rays from camera centre (ox, 0, 0) with a layer's plane.

  Args:
    layer: the layer.
    ox: x of the camera centre (0 for left, baseline for right).
    rx: `(x - cx) / fx`, float32, broadcastable against `ry` (e.g. [1, w] and [h, 1]).
    ry: `(y - cy) / fx`, float32.

  Returns:
    (depth, tu, tv, hit): depth Z of the hit (inf/negative where the plane is missed),
    texel coordinates relative to the layer centre, and the boolean shape-and-front
    test; all of the broadcast shape.
  """
  n, e1, e2 = layer.normal, layer.e1, layer.e2
  d = np.array([ox, 0.0, 0.0]) - layer.center
  # Ray X = O + Z * (rx, ry, 1): its plane crossing has Z = n.(C - O) / n.(rx, ry, 1).
  num = -float(n @ d)
  with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
    depth = num / (float(n[0]) * rx + (float(n[1]) * ry + float(n[2])))
    tu = float(e1 @ d) + depth * (float(e1[0]) * rx + (float(e1[1]) * ry + float(e1[2])))
    tv = float(e2 @ d) + depth * (float(e2[0]) * rx + (float(e2[1]) * ry + float(e2[2])))
    hit = depth > 0
    if layer.kind != "background":
      hit &= np.isfinite(depth)
      hit &= inside(layer.kind, layer.params, tu, tv)
  return depth, tu, tv, hit


def inside(kind: str, params: tuple, u: np.ndarray, v: np.ndarray) -> np.ndarray:
  """Point-in-shape test in texel coordinates relative to the shape's centre."""
  if kind == "rectangle":
    a, b = params
    return (np.abs(u) <= a) & (np.abs(v) <= b)
  if kind == "ellipse":
    a, b = params
    return (u * (1.0 / a)) ** 2 + (v * (1.0 / b)) ** 2 <= 1.0
  # Star-shaped polygon: find the angular sector of each point, then test it against
  # that sector's edge (vertices are in counter-clockwise angular order).
  angles, px, py = params
  k = len(angles)
  sector = (np.searchsorted(angles, np.arctan2(v, u)) - 1) % k
  ax, ay = px[sector], py[sector]
  bx, by = px[(sector + 1) % k], py[(sector + 1) % k]
  return (bx - ax) * (v - ay) - (by - ay) * (u - ax) >= 0


def bbox(layer: Layer, ox: float, cam: Camera, h: int, w: int):
  """Pixel box (y0, y1, x0, x1) that contains the layer's image, or None if empty."""
  if layer.kind == "background":
    return 0, h, 0, w
  # The shape lies in its texel box; the projection of that planar box is the convex
  # hull of its projected corners (all are in front of the camera by construction).
  umin, umax, vmin, vmax = layer.extent
  inv_scale2 = 1.0 / float(layer.e1 @ layer.e1)  # e1, e2 have length texels/metre
  tuv = np.array([[umin, vmin], [umin, vmax], [umax, vmin], [umax, vmax]]) * inv_scale2
  corners = layer.center + tuv @ np.stack([layer.e1, layer.e2])
  xs = cam.fx * (corners[:, 0] - ox) / corners[:, 2] + cam.cx
  ys = cam.fx * corners[:, 1] / corners[:, 2] + cam.cy
  x0, x1 = max(int(np.floor(xs.min())) - 1, 0), min(int(np.ceil(xs.max())) + 2, w)
  y0, y1 = max(int(np.floor(ys.min())) - 1, 0), min(int(np.ceil(ys.max())) + 2, h)
  if x0 >= x1 or y0 >= y1:
    return None
  return y0, y1, x0, x1


def render_view(layers, ox: float, cam: Camera, rx: np.ndarray, ry: np.ndarray):
  """Z-buffered ray casting of one view.

  Args:
    layers: list of `Layer`, background first.
    ox: camera centre x (0 left, baseline right).
    cam: intrinsics.
    rx: [1, W] normalised x; ry: [H, 1] normalised y.

  Returns:
    rgba [H, W, 4] uint8 (alpha unused), depth [H, W] float32, segmentation
    [H, W] uint8 (0 background, k object k).
  """
  h, w = ry.shape[0], rx.shape[1]
  rgba = np.zeros((h, w, 4), np.uint8)
  # One uint32 per pixel: masked copies of whole RGBA pixels are then a single
  # 2-D `copyto`, far faster than a broadcast 3-D mask.
  rgba32 = rgba.view(np.uint32)[..., 0]
  depth = np.full((h, w), np.inf, np.float32)
  seg = np.zeros((h, w), np.uint8)
  for k, layer in enumerate(layers):
    box = bbox(layer, ox, cam, h, w)
    if box is None:
      continue
    y0, y1, x0, x1 = box
    z, tu, tv, hit = cast(layer, ox, rx[:, x0:x1], ry[y0:y1])
    col = lookup(layer, tu, tv)
    if k == 0:  # the background is built to be hit everywhere: no z-test needed
      depth[...], rgba[...] = z, col
      continue
    zbuf = depth[y0:y1, x0:x1]
    hit &= z < zbuf
    np.copyto(zbuf, z, where=hit)
    np.copyto(rgba32[y0:y1, x0:x1], col.view(np.uint32)[..., 0], where=hit)
    np.copyto(seg[y0:y1, x0:x1], k, where=hit)
  return rgba, depth, seg


def lookup(layer: Layer, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
  """Bilinear RGBA texture lookup at texel offsets (tu, tv) from the layer centre."""
  size = np.float32(layer.texture.shape[0])
  tu += np.float32(layer.origin[0])
  tv += np.float32(layer.origin[1])
  if layer.kind == "background":
    # The background plane is unbounded; reduce coordinates to one period because
    # cv2.remap takes a slow per-pixel path for coordinates outside the texture.
    tu -= size * np.floor(tu * (1 / size))
    tv -= size * np.floor(tv * (1 / size))
  return cv2.remap(layer.texture, tu, tv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def valid_mask(layers, depth, seg, cam: Camera, ry: np.ndarray):
  """Left pixels whose 3D point is inside the right image and not occluded there.

  The occlusion test is analytic: the ray from the right camera through the exact
  right-image position `x - d` (not a rounded pixel) is intersected with every other
  layer that could be nearer; any hit with a smaller depth occludes the point.

  Args:
    layers: list of `Layer`, background first.
    depth: [H, W] left depth; seg: [H, W] left layer ids.
    cam: intrinsics.
    ry: [H, 1] normalised y.

  Returns:
    [H, W] bool.
  """
  h, w = depth.shape
  fb = cam.fx * cam.baseline
  xr = np.arange(w, dtype=np.float32)[None, :] - np.float32(fb) / depth
  valid = (xr >= 0) & (xr <= w - 1)
  for j, layer in enumerate(layers):
    # Objects are always nearer than the background's nearest point (their
    # disparity bands do not overlap), so the background never occludes.
    box = None if layer.kind == "background" else bbox(layer, cam.baseline, cam, h, w)
    if box is None:
      continue
    y0, y1, x0, x1 = box
    xs, zs, ok = xr[y0:y1], depth[y0:y1], valid[y0:y1]
    cand = (xs >= x0 - 1) & (xs <= x1) & (zs > layer.zmin) & (seg[y0:y1] != j) & ok
    idx = np.flatnonzero(cand)
    if idx.size == 0:
      continue
    rxs = (xs.ravel()[idx] - np.float32(cam.cx)) * np.float32(1 / cam.fx)
    z, _, _, hit = cast(layer, cam.baseline, rxs, ry[y0 + idx // w, 0])
    # Relative tolerance: a plane cannot occlude itself, so ties are measure-zero
    # plane intersections; 1e-5 only absorbs float32 rounding.
    occluded = hit & (z < zs.ravel()[idx] * np.float32(1 - 1e-5))
    ok.ravel()[idx[occluded]] = False
  return valid
