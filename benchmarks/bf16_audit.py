"""Where bfloat16 compute departs from float32, module by module: forward and gradients.

    python benchmarks/bf16_audit.py                      # forward, fixtures at ../shared/fixtures
    python benchmarks/bf16_audit.py --parts --gradients  # each module alone; training gradients

Forward: the fixture clip (`golden_small`: 1x3x64x128, iters=4, make_weights.py seed 0), the
final disparity's mean and max absolute difference from the float32 model (at "highest"),
for the bfloat16 model and for the float32 model with its parameters rounded to bfloat16 (the
floor: every bfloat16 product starts from those rounded weights); with `--parts` also with one
module at a time in bfloat16 (the rest float32): the depth prior, fnet, cnet, and the update
block's motion encoder, time attention, space attention, GRU, flow head and mask head; and
everything but the flow head in bfloat16.

Gradients (`--gradients`): the training loss (`train/loss.py`, every prediction) on
`benchmarks/gradient_check.py`'s clip (1x2x32x64 uniform frames by default, `--frames`,
`--height`, `--width`; the right one the left shifted by 3 px, iters=2, ground truth
3 + 2 sin(x / 5) px with an invalid corner),
differentiated with respect to every parameter and both frames: the relative L2 difference
from float32 per parameter group (kernels, biases, norm scales), for bfloat16 and for the
rounded-parameter float32 floor. Biases in front of an instance norm have a gradient of 0
(float32 noise, ~1e-9) and are left out. Each gradient compiles for minutes on a 2-core CPU.
Measures, asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import jax.numpy as jnp  # noqa: E402  pylint: disable=wrong-import-position
import numpy as np  # noqa: E402  pylint: disable=wrong-import-position

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model import update  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.depth import DepthExtractor  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.encoder import BasicEncoder  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.layers import CorrMLP, conv  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import json_output_problem  # noqa: E402  pylint: disable=wrong-import-position
import gradient_check  # noqa: E402  benchmarks/gradient_check.py
from timing import (  # noqa: E402  benchmarks/timing.py
    check_clip_arguments, fixtures_folder, make_weights_module)

# Modules whose compute dtype can be set alone; "carry" is the GRU state between steps.
PARTS = ("depth", "fnet", "cnet", "encoder", "time", "space", "gru", "flow", "mask", "carry")


def dtypes(default: str, **one) -> tuple:
  """`((part, dtype name), ...)`: every part in `default` but those named."""
  return tuple(sorted({**{p: default for p in PARTS}, **one}.items()))


@functools.lru_cache(maxsize=None)
def mixed_classes():
  """`(MixedUpdate, MixedModel)`, defined on first use (Flax modules are dataclasses,
  which need their module in `sys.modules`: a script run as `__main__` has it)."""

  class MixedUpdate(update.SequenceUpdateBlock3D):
    """The update block with a compute dtype per part (`parts`); the state carried in `dtype`."""

    parts: tuple = ()

    def setup(self):
      d = {k: jnp.dtype(v) for k, v in self.parts}
      self.encoder = update.BasicMotionEncoder(d["encoder"])
      self.time_attn = update.TimeAttnBlock(256, d["time"])
      self.space_attn = update.SpaceAttnBlock(256, d["space"], self.block_mb)
      self.gru = update.SKSepConvGRU3D(self.hidden_dim, d["gru"], "direct", self.block_mb)
      self.flow_head = update.FlowHead3D(d["flow"])
      self.mask3d_0 = conv(256, (3, 3, 3), 1, 1, dtype=d["mask"])
      self.mask3d_2 = conv(27 * self.mask_size ** 2, (1, 1, 1), 1, 0, dtype=d["mask"])

    def __call__(self, net, inp, corr, flow, with_mask=True):
      net, mask, delta = super().__call__(net, inp, corr, flow, with_mask)
      return net.astype(self.dtype), mask, delta

  class MixedModel(sav_jax.StereoAnyVideo):
    """`StereoAnyVideo` (same parameters) with a compute dtype per part (`parts`)."""

    parts: tuple = ()

    def setup(self):
      d = dict(self.parts)
      cfg = self.cfg
      self.cnet = BasicEncoder(cfg.fnet_dim, jnp.dtype(d["cnet"]))
      self.fnet = BasicEncoder(cfg.fnet_dim, jnp.dtype(d["fnet"]))
      self.depthnet = DepthExtractor(dataclasses.replace(cfg, dtype=d["depth"]))
      self.corr_mlp = CorrMLP()
      self.update_block = MixedUpdate(cfg.hidden_dim, cfg.upsample_rate, jnp.dtype(d["carry"]),
                                      cfg.frame_block_mb, "direct", parts=self.parts)

  return MixedUpdate, MixedModel


def model_for(parts: tuple):
  """`StereoAnyVideo` (same parameters) with a compute dtype per part (`parts`)."""
  cfg = sav_jax.SAVConfig(dtype=dict(parts)["carry"], gru_conv="direct",
                          vit_attention="blocked")
  return mixed_classes()[1](cfg, parts=parts)


def rounded(tree, dtype=jnp.bfloat16):
  """Every array of `tree` rounded to `dtype` and back."""
  return jax.tree_util.tree_map(lambda a: jnp.asarray(a).astype(dtype).astype(a.dtype), tree)


def forward_rows(variables, left, right, parts: bool) -> list[dict]:
  """The final disparity of each mode against the float32 model's (fixture clip)."""
  def run(mode, params=variables):
    model = model_for(mode)
    fwd = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=4, final_only=True).disparities)
    with jax.default_matmul_precision("highest"):
      return np.asarray(fwd(params, left, right))

  ref = run(dtypes("float32"))
  modes = [("bfloat16", dtypes("bfloat16"), variables),
           ("float32, parameters rounded to bfloat16", dtypes("float32"), rounded(variables))]
  if parts:
    modes += [(f"{p} alone in bfloat16", dtypes("float32", **{p: "bfloat16"}), variables)
              for p in PARTS if p != "carry"]
    modes.append(("bfloat16 but the flow head", dtypes("bfloat16", flow="float32"), variables))
  rows = []
  for name, mode, params in modes:
    start = time.perf_counter()
    err = np.abs(run(mode, params) - ref)
    rows.append(dict(mode=name, mean_px=float(err.mean()), max_px=float(err.max()),
                     seconds=time.perf_counter() - start))
    print(f"  {name:<42}{rows[-1]['mean_px']:>10.4f}{rows[-1]['max_px']:>10.4f}", flush=True)
  return rows


def gradient_clip(t: int, h: int, w: int):
  """benchmarks/gradient_check.py's frames and training-loss ground truth (`t` frames of
  `h` x `w`): `(left, right, disparity, valid)`."""
  size = argparse.Namespace(frames=t, height=h, width=w)
  return (*gradient_check.frames(size), *gradient_check.ground_truth(size))


def gradients(mode, params, clip):
  from train.loss import sequence_loss  # pylint: disable=import-outside-toplevel
  left, right, disparity, valid = clip
  model = model_for(mode)

  def loss(p, l, r):
    out = model.apply({"params": p}, l, r, iters=2).disparities
    return sequence_loss(out, disparity, valid)[0]

  with jax.default_matmul_precision("highest"):
    return jax.device_get(jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(params, left, right))


def group_of(path) -> tuple[str, str]:
  """`(module group, kind)` of a parameter path: update-block parts and depthnet.conv
  separately; kind kernel, bias (LayerScale's gamma too) or scale."""
  keys = [str(getattr(k, "key", k)) for k in path]
  top = "/".join(keys[:2]) if keys[0] in ("update_block", "depthnet") else keys[0]
  kind = {"gamma": "bias"}.get(keys[-1], keys[-1])
  return top, kind


def gradient_rows(variables, modes, size) -> list[dict]:
  """Relative L2 differences of the gradients of each mode from float32's, by group, on
  the clip of `size` (T, H, W)."""
  clip = gradient_clip(*size)
  params = variables["params"]
  ref_p, ref_l, ref_r = gradients(dtypes("float32"), params, clip)
  ref_leaves = jax.tree_util.tree_leaves(ref_p)
  rows = []
  for name, mode, p in modes:
    start = time.perf_counter()
    got_p, got_l, got_r = gradients(mode, p, clip)
    sums = collections.defaultdict(lambda: [0.0, 0.0])
    for (path, got), want in zip(jax.tree_util.tree_flatten_with_path(got_p)[0], ref_leaves):
      want = np.asarray(want, np.float64)
      if not np.any(np.abs(want) > 1e-6):  # biases in front of an instance norm: 0
        continue
      group, kind = group_of(path)
      for key in (f"{group} {kind}", f"all {kind}"):
        sums[key][0] += float(np.sum((np.asarray(got, np.float64) - want) ** 2))
        sums[key][1] += float(np.sum(want ** 2))
    row = {"mode": name, "seconds": time.perf_counter() - start}
    for key, frames_got, frames_want in (("left frames", got_l, ref_l),
                                         ("right frames", got_r, ref_r)):
      row[key] = float(np.linalg.norm(frames_got - frames_want) / np.linalg.norm(frames_want))
    row.update({k: (d / n) ** 0.5 for k, (d, n) in sorted(sums.items()) if n > 0})
    rows.append(row)
  return rows


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--fixtures", default=str(fixtures_folder()), help="the oracle fixtures folder")
  p.add_argument("--parts", action="store_true",
                 help="also each module alone in bfloat16 (forward; with --gradients, gradients too)")
  p.add_argument("--gradients", action="store_true",
                 help="also the training gradients (each compiles for minutes on a CPU)")
  p.add_argument("--frames", type=int, default=2, help="the gradients' clip: frames")
  p.add_argument("--height", type=int, default=32, help="the gradients' clip: height")
  p.add_argument("--width", type=int, default=64, help="the gradients' clip: width")
  p.add_argument("--json", help="write the rows to this JSON file (a new file, or --overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  a = p.parse_args(argv)
  problem = json_output_problem(a.json, a.overwrite) if a.json else None
  if problem:  # before the long run
    p.error(problem)
  if a.gradients:  # the gradients' clip (iters=2): the model would refuse it after the forward rows
    check_clip_arguments(p, a)
  fixtures = pathlib.Path(a.fixtures)
  state = make_weights_module(fixtures, "bf16_audit.py").make_state_dict(
      str(fixtures / "sav_manifest.json"), 0)
  variables = sav_jax.convert.params_from_state_dict(state, sav_jax.SAVConfig())
  golden = np.load(fixtures / "golden_small.npz")
  left, right = (jnp.asarray(np.moveaxis(golden[f"input_{v}"], -3, -1)) for v in ("left", "right"))
  device = jax.devices()[0]
  print(f"device {device.platform}:{device.device_kind} (jax {jax.__version__}); final "
        "disparity against the float32 model's, fixture clip 1x3x64x128 iters=4")
  print(f"  {'mode':<42}{'mean px':>10}{'max px':>10}")
  result = {"device": f"{device.platform}:{device.device_kind}", "jax": jax.__version__,
            "forward": forward_rows(variables, left, right, a.parts)}
  if a.gradients:
    modes = [("bfloat16", dtypes("bfloat16"), variables["params"]),
             ("float32, parameters rounded to bfloat16", dtypes("float32"),
              rounded(variables["params"]))]
    if a.parts:
      modes += [(f"{q} alone in bfloat16", dtypes("float32", **{q: "bfloat16"}),
                 variables["params"]) for q in PARTS if q != "carry"]
    size = (a.frames, a.height, a.width)
    print(f"training gradients (1x{a.frames}x{a.height}x{a.width}, iters=2): relative L2 "
          "difference from float32")
    result["gradients"] = gradient_rows(variables, modes, size)
    for row in result["gradients"]:
      print(f"  {row['mode']}:")
      for k, v in row.items():
        if k not in ("mode", "seconds"):
          print(f"    {k:<40}{v:>8.4f}")
  if a.json:
    with open(a.json, "w", encoding="utf-8") as f:
      json.dump(result, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
