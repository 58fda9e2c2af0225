"""Where the forward time goes: times each stage of the model separately (compiled).

    python benchmarks/stage_times.py --frames 5 --height 128 --width 256
    python benchmarks/stage_times.py --frames 20 --height 720 --width 1280 --iters 20 \
        --dtype bfloat16                                   # the paper's window (GPU)

Prints the median time of: the depth prior (VDA), the fnet/cnet encoders, the whole
feature stage, one refinement step at each scale as inference runs it (correlation + MLP +
update block, no mask head), the update block alone at 1/4 and its parts (in the compute
dtype, as in the model), and the sum `features + iters/2 * (s16 + s8) + iters * s4` to
hold against `sav-jax bench` (the final convex upsampling is left out). Each stage is
compiled on its own, so the figures are wall-clock times on any backend.
"""

import argparse
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import jax.numpy as jnp
import numpy as np

import sav_jax
import sav_jax.ops.pool
from sav_jax.config import resolve_vit_attention
from sav_jax.model.init import init_variables
from sav_jax.model.stereo_any_video import StereoAnyVideo
from sav_jax.model import update as U
from sav_jax.model.layers import CorrMLP
from sav_jax.ops.correlation import WIDE_WINDOW, aapc

from timing import check_clip_arguments, timed  # benchmarks/timing.py


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--frames", type=int, default=5)
  p.add_argument("--height", type=int, default=128)
  p.add_argument("--width", type=int, default=256)
  p.add_argument("--iters", type=int, default=8, help="for the summed total")
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
  a = p.parse_args()
  check_clip_arguments(p, a)
  cfg = sav_jax.SAVConfig(dtype=a.dtype)
  model = StereoAnyVideo(cfg)
  v = jax.device_put(init_variables(cfg))
  rng = np.random.default_rng(0)
  left = jnp.asarray(rng.uniform(0, 255, (1, a.frames, a.height, a.width, 3)), jnp.float32)
  right = jnp.roll(left, -4, axis=3)

  depth = jax.jit(lambda v, x: model.apply(v, x, method=lambda m, x: m.depthnet(x)))
  enc = jax.jit(lambda v, x: model.apply(
      v, x.reshape(-1, *x.shape[2:]), method=lambda m, x: (m.fnet(x), m.cnet(x))))
  feats = jax.jit(lambda v, l, r: model.apply(v, l, r, method=StereoAnyVideo.features))
  both = jnp.concatenate([left, right])
  print(f"depth prior (both views)  {timed(depth, v, both):.3f} s  (ViT attention "
        f"{resolve_vit_attention(cfg.vit_attention, cfg.compute_dtype)})")
  vit = jax.jit(lambda v, x: model.apply(
      v, x.reshape(-1, *x.shape[2:]), method=lambda m, x: m.depthnet.tokens(x)))
  print(f"  of which the ViT          {timed(vit, v, both):.3f} s")
  print(f"fnet + cnet (both views)  {timed(enc, v, both):.3f} s")
  total = timed(feats, v, left, right)
  print(f"feature stage (as run)    {total:.3f} s")
  f1, f2, ctx = feats(v, left, right)
  dtype = jnp.dtype(a.dtype)
  for pool, name, count in ((4, "1/16", a.iters // 2), (2, "1/8", a.iters // 2),
                            (1, "1/4", a.iters)):
    s = lambda x: x if pool == 1 else sav_jax.ops.pool.avg_pool(x, pool)  # noqa: E731
    args = (jnp.tanh(s(ctx)).astype(dtype), jnp.zeros(s(f1).shape[:-1] + (1,)),
            jax.nn.relu(s(ctx)), s(f1), s(f2))
    step = jax.jit(lambda v, *xs: model.apply(
        v, *xs, method=lambda m, *xs: m.step(*xs, WIDE_WINDOW, with_up=False)))
    seconds = timed(step, v, *args)
    total += count * seconds
    print(f"one refinement step {name:5s} {seconds:.3f} s  (x{count})")
  print(f"sum for iters={a.iters}        {total:.3f} s  (compare with sav-jax bench)")
  net = args[0]
  ub = jax.jit(lambda v, n, i, c, fl: model.apply(
      v, n, i, c, fl, method=lambda m, *xs: m.update_block(*xs)))
  print(f"update block alone 1/4    {timed(ub, v, net, args[2], args[2], jnp.zeros(net.shape[:-1] + (1,))):.3f} s")
  update_block_parts(v["params"], net.shape[:-1], dtype)


def update_block_parts(params, lead, dtype=jnp.float32):
  """Times the parts of one 1/4 update (inference: no mask head), each compiled alone in
  the compute `dtype` (the correlation and its MLP stay float32, as in the model)."""
  rng = np.random.default_rng(0)
  r = lambda c: jnp.asarray(rng.standard_normal((*lead, c)), dtype)  # noqa: E731
  ub = params["update_block"]
  b, t, h, w = lead
  f1, f2 = (r(128).astype(jnp.float32).reshape(b * t, h, w, 128) for _ in range(2))
  disp = jnp.asarray(rng.uniform(0, 5, (b * t, h, w)), jnp.float32)
  parts = [
      ("AAPC 1x9 (warp + window correlation)",
       lambda p, a, c, d: aapc(a, c, d, WIDE_WINDOW, 4), (f1, f2, disp)),
      ("corr MLP", lambda p, c: CorrMLP().apply({"params": p}, c),
       (r(324).astype(jnp.float32),)),
      ("motion encoder", lambda p, f, c: U.BasicMotionEncoder(dtype=dtype).apply(
          {"params": p}, f, c), (r(1), r(128))),
      ("time attention", lambda p, x: U.TimeAttnBlock(dtype=dtype).apply({"params": p}, x),
       (r(256),)),
      ("space attention (linear)", lambda p, x: U.SpaceAttnBlock(dtype=dtype).apply(
          {"params": p}, x), (r(256),)),
      ("separable 3-D GRU", lambda p, n, x: U.SKSepConvGRU3D(dtype=dtype).apply(
          {"params": p}, n, x), (r(128), r(256))),
      ("3x3x3 flow head", lambda p, n: U.FlowHead3D(dtype=dtype).apply({"params": p}, n),
       (r(128),)),
  ]
  names = (None, "corr_mlp", "encoder", "time_attn", "space_attn", "gru", "flow_head")
  for (label, fn, xs), name in zip(parts, names):
    p = params["corr_mlp"] if name == "corr_mlp" else (ub[name] if name else None)
    print(f"  {label:38s} {timed(jax.jit(fn), p, *xs):.3f} s")


if __name__ == "__main__":
  main()
