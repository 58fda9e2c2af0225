"""Rewrites of the 1/4 update block's parts (and the ViT attention), timed against the model's
own modules on the same weights and inputs.

    python benchmarks/update_variants.py --frames 20 --height 720 --width 1280 --dtype bfloat16

Each row is compiled alone and timed (median of 3 calls after a warm-up); `max diff` is the
largest absolute difference from the model's module on the same inputs (the rewrites are
the same arithmetic regrouped, so it is rounding only). The parts are the ones
`stage_times.py` lists; the variants:

- GRU: the z and r convolutions that read the same input as one convolution with both
  kernels side by side (and the super kernel's second convs as one grouped convolution);
- flow head: XLA's native 3-D convolution instead of per-frame 2-D taps; the narrowing
  256 -> 2 conv as three convolutions, one per temporal tap (the model's form before it
  took them as one 256 -> 6 convolution);
- space attention: all frames at once (the model runs them in blocks of frames under
  `SAVConfig.frame_block_mb`: at the paper's window in bfloat16, two blocks of 10); q, k
  and v as one 256 -> 768 product (the model's form from 2026-11-30 to 2026-12-04, adopted
  from a comparison that this row's blocking confounded); the linear attention's per-head
  products batched over the heads
  (the model's form before it took them as two plain products, see `update.linear_attention`);
- time attention: `jax.nn.dot_product_attention` (cuDNN on a GPU in bfloat16, else XLA's);
  the T x T products as broadcast multiply-and-sum in float32 over `[B, T, h*w, heads, d]`
  (no transposes, no batched matrix products: reductions XLA can fuse);
- GRU: the convolutions of `[h, x]` split into one of h and one of x (no concatenated
  input), the x parts of a pass that share a kernel size as one convolution;
- motion encoder: the 7x7 flow convolution over both flow channels (the y one zero; the
  model reads the x channel only since 2026-12-04), and as one product of the 49 taps;
- warp, correlation and correlation MLP: the maps (and/or the MLP) in the compute dtype
  instead of float32 (changes the bfloat16 mode's numbers: see `precision_check.py`).
- depth prior: the ViT attention blocked (default) or cuDNN's fused kernel (GPU, bfloat16).
"""

import argparse
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import jax.numpy as jnp
import numpy as np

import sav_jax
from sav_jax.config import resolve_vit_attention
from sav_jax.model import update as U
from sav_jax.model.init import init_variables
from sav_jax.model.layers import Conv3D, CorrMLP, conv2d, gelu, layer_norm
from sav_jax.model.stereo_any_video import StereoAnyVideo
from sav_jax.ops.correlation import WIDE_WINDOW, window_correlation
from sav_jax.ops.sample import warp_x

from timing import add_clip_arguments, timed  # benchmarks/timing.py


def _kb(p, names, dtype):
  """Kernels and biases of the named convs, concatenated along the output channels."""
  k = jnp.concatenate([p[n]["kernel"] for n in names], axis=-1).astype(dtype)
  b = jnp.concatenate([p[n]["bias"] for n in names], axis=-1).astype(dtype)
  return k, b


def _conv_axis(y, kernel, bias, axis, groups=1):
  """A 1-D kernel `[1,1,k]`/`[1,k,1]`/`[k,1,1]` conv of `[B,T,H,W,C]` along W, H or T."""
  b, t, h, w, c = y.shape
  k = kernel.shape[axis]
  pad = ((k - 1) // 2,) * 2
  if axis == 2:  # W
    x2, k2, padding = y.reshape(b * t, h, w, c), kernel[0], ((0, 0), pad)
  elif axis == 1:  # H
    x2, k2, padding = y.reshape(b * t, h, w, c), kernel[0], (pad, (0, 0))
  else:  # T
    x2, k2, padding = y.reshape(b, t, h * w, c), kernel[:, 0], (pad, (0, 0))
  out = jax.lax.conv_general_dilated(x2, k2, (1, 1), padding,
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                     feature_group_count=groups)
  return (out + bias).reshape(b, t, h, w, -1)


def gru_fused(p, h, x, dtype):
  """`SKSepConvGRU3D` with the z/r convolutions of one input as one convolution."""
  h, x = h.astype(dtype), x.astype(dtype)
  hd = h.shape[-1]

  def update(h, zr, qname, axis):
    z, r = jax.nn.sigmoid(zr[..., :hd]), jax.nn.sigmoid(zr[..., hd:])
    kq, bq = _kb(p, [qname], dtype)
    q = jnp.tanh(_conv_axis(jnp.concatenate([r * h, x], -1), kq, bq, axis))
    return (1 - z) * h + z * q

  k1, b1 = _kb(p, ["convz1_0", "convr1_0"], dtype)
  zr = gelu(_conv_axis(jnp.concatenate([h, x], -1), k1, b1, 2))
  k2, b2 = _kb(p, ["convz1_2", "convr1_2"], dtype)
  zr = _conv_axis(zr, k2, b2, 2, groups=2)
  h = update(h, zr, "convq1", 2)
  for stage, axis in (("2", 1), ("3", 0)):
    k, bias = _kb(p, [f"convz{stage}", f"convr{stage}"], dtype)
    h = update(h, _conv_axis(jnp.concatenate([h, x], -1), k, bias, axis), f"convq{stage}", axis)
  return h


def flow_head_native(p, x, dtype):
  """`FlowHead3D` with XLA's 3-D convolutions."""
  def c3(y, name):
    return jax.lax.conv_general_dilated(
        y, p[name]["kernel"].astype(dtype), (1, 1, 1), [(1, 1)] * 3,
        dimension_numbers=("NDHWC", "DHWIO", "NDHWC")) + p[name]["bias"].astype(dtype)
  return c3(jax.nn.relu(c3(x.astype(dtype), "conv1")), "conv2")


def flow_head_per_tap(p, x, dtype):
  """`FlowHead3D` with the narrowing conv as one convolution per temporal tap."""
  y = jax.nn.relu(Conv3D(256, (3, 3, 3), (1, 1, 1), dtype=dtype).apply({"params": p["conv1"]}, x))
  b, t, h, w, c = y.shape
  k = p["conv2"]["kernel"].astype(dtype)  # [3, 3, 3, 256, 2]
  frames = y.reshape(b * t, h, w, c)
  tap = lambda i: conv2d(frames, k[i], ((1, 1), (1, 1))).reshape(b, t, h, w, -1)  # noqa: E731
  zero = jnp.zeros((b, 1, h, w, k.shape[-1]), dtype)
  out = (tap(1) + jnp.concatenate([zero, tap(0)[:, :-1]], axis=1)
         + jnp.concatenate([tap(2)[:, 1:], zero], axis=1))
  return out + p["conv2"]["bias"].astype(dtype)


def linear_attention_per_head(q, k, v, eps=1e-6):
  """`update.linear_attention` as LoFTR writes it: batched per-head products (the model's
  form before it took the heads' products as two plain matrix products)."""
  q, k = jax.nn.elu(q) + 1, jax.nn.elu(k) + 1
  length = v.shape[1]
  kv = jnp.einsum("nshd,nshv->nhdv", k, v / length)
  z = 1.0 / (jnp.einsum("nlhd,nhd->nlh", q, k.sum(axis=1)) + eps)
  return jnp.einsum("nlhd,nhdv,nlh->nlhv", q, kv, z) * length


def space_attn_rewrite(p, x, dtype, fused_qkv=False, attention=U.linear_attention):
  """`SpaceAttnBlock` with all frames at once, with q, k and v as one product
  (`fused_qkv`) and/or another linear attention."""
  p = p["encoder_layer"]
  b, t, h, w, c = x.shape
  x = x.reshape(b * t, h * w, c).astype(dtype)
  dense = lambda y, n: y @ p[n]["kernel"].astype(dtype)  # noqa: E731
  split = lambda y: y.reshape(b * t, h * w, 8, c // 8)  # noqa: E731
  if not fused_qkv:
    q, k, v = (dense(x, f"{n}_proj") for n in "qkv")
  else:
    q, k, v = jnp.split(x @ jnp.concatenate([p[f"{n}_proj"]["kernel"] for n in "qkv"],
                                            axis=-1).astype(dtype), 3, axis=-1)
  msg = attention(split(q), split(k), split(v)).reshape(b * t, h * w, c)
  norm = lambda y, n: layer_norm(dtype=dtype).apply({"params": p[n]}, y)  # noqa: E731
  msg = norm(dense(msg, "merge"), "norm1")
  msg = dense(jax.nn.relu(dense(jnp.concatenate([x, msg], -1), "mlp_0")), "mlp_2")
  return (x + norm(msg, "norm2")).reshape(b, t, h, w, c)


def time_attn_dpa(p, x, dtype, implementation):
  """`TimeAttnBlock` with `jax.nn.dot_product_attention` over time."""
  b, t, h, w, c = x.shape
  y = layer_norm(dtype=dtype).apply({"params": p["temporal_norm1"]}, x)
  seq = y.reshape(b, t, h * w, 8, c // 8).transpose(0, 2, 1, 3, 4).reshape(b * h * w, t, 8, -1)
  out = jax.nn.dot_product_attention(seq, seq, seq, implementation=implementation)
  out = out.reshape(b, h * w, t, c).transpose(0, 2, 1, 3).reshape(b, t, h, w, c)
  out = out @ p["temporal_attn"]["proj"]["kernel"].astype(dtype) + \
      p["temporal_attn"]["proj"]["bias"].astype(dtype)
  out = out @ p["temporal_fc"]["kernel"].astype(dtype) + p["temporal_fc"]["bias"].astype(dtype)
  return x + out


def time_attn_fused(p, x, dtype):
  """`TimeAttnBlock` with the T x T products as float32 broadcast multiply-and-sum over
  `[B, T, h*w, heads, d]` (reductions, no transposes or batched matrix products)."""
  b, t, h, w, c = x.shape
  y = layer_norm(dtype=dtype).apply({"params": p["temporal_norm1"]}, x)
  f = y.reshape(b, t, h * w, 8, c // 8).astype(jnp.float32)
  logits = jnp.sum(f[:, :, None] * f[:, None], axis=-1) * (c // 8) ** -0.5  # [b,t,s,P,n]
  attn = jax.nn.softmax(logits, axis=2)
  out = jnp.sum(attn[..., None] * f[:, None], axis=2).astype(dtype).reshape(b, t, h, w, c)
  out = out @ p["temporal_attn"]["proj"]["kernel"].astype(dtype) + \
      p["temporal_attn"]["proj"]["bias"].astype(dtype)
  out = out @ p["temporal_fc"]["kernel"].astype(dtype) + p["temporal_fc"]["bias"].astype(dtype)
  return x + out


def gru_split(p, h, x, dtype):
  """`SKSepConvGRU3D` with every convolution of `[h, x]` as one of h plus one of x (no
  concatenated input); a pass's x parts with the same kernel size run as one convolution."""
  h, x = h.astype(dtype), x.astype(dtype)
  hd = h.shape[-1]
  k_ = lambda n, part: (p[n]["kernel"][..., :hd, :] if part == "h"  # noqa: E731
                        else p[n]["kernel"][..., hd:, :]).astype(dtype)
  b_ = lambda n: p[n]["bias"].astype(dtype)  # noqa: E731
  cat = lambda *a: jnp.concatenate(a, axis=-1)  # noqa: E731
  # W pass: z/r super kernels (15 taps, GELU, 5 taps), q (5 taps).
  pre = (_conv_axis(h, cat(k_("convz1_0", "h"), k_("convr1_0", "h")), 0.0, 2)
         + _conv_axis(x, cat(k_("convz1_0", "x"), k_("convr1_0", "x")),
                      cat(b_("convz1_0"), b_("convr1_0")), 2))
  pre = gelu(pre)
  z = jax.nn.sigmoid(_conv_axis(pre[..., :hd], p["convz1_2"]["kernel"].astype(dtype),
                                b_("convz1_2"), 2))
  r = jax.nn.sigmoid(_conv_axis(pre[..., hd:], p["convr1_2"]["kernel"].astype(dtype),
                                b_("convr1_2"), 2))
  q = jnp.tanh(_conv_axis(r * h, k_("convq1", "h"), 0.0, 2)
               + _conv_axis(x, k_("convq1", "x"), b_("convq1"), 2))
  h = (1 - z) * h + z * q
  for stage, axis in (("2", 1), ("3", 0)):
    zn, rn, qn = (f"conv{g}{stage}" for g in "zrq")
    xs = _conv_axis(x, cat(k_(zn, "x"), k_(rn, "x"), k_(qn, "x")), cat(b_(zn), b_(rn), b_(qn)),
                    axis)
    hzr = _conv_axis(h, cat(k_(zn, "h"), k_(rn, "h")), 0.0, axis)
    z = jax.nn.sigmoid(hzr[..., :hd] + xs[..., :hd])
    r = jax.nn.sigmoid(hzr[..., hd:] + xs[..., hd:2 * hd])
    q = jnp.tanh(_conv_axis(r * h, k_(qn, "h"), 0.0, axis) + xs[..., 2 * hd:])
    h = (1 - z) * h + z * q
  return h


def motion_encoder_rewrite(p, flow, corr, dtype, convf1):
  """`BasicMotionEncoder` (the model passes the x-flow `[..., 1]`) with the 7x7 flow
  convolution over both flow channels, the y one zero (`convf1="xy"`: the model's form
  before 2026-12-04) or as one product of its 49 shifted taps (`convf1="taps"`)."""
  *lead, h, w, _ = corr.shape
  frames = lambda y: y.reshape(-1, h, w, y.shape[-1])  # noqa: E731

  def c(y, name, pad, kernel=None):
    k = (p[name]["kernel"] if kernel is None else kernel).astype(dtype)
    return conv2d(y, k, ((pad, pad), (pad, pad))) + p[name]["bias"].astype(dtype)

  flow = jnp.concatenate([frames(flow), jnp.zeros_like(frames(flow))], axis=-1)
  cor = jax.nn.relu(c(frames(corr).astype(dtype), "convc1", 0))
  cor = jax.nn.relu(c(cor, "convc2", 1))
  if convf1 == "xy":
    flo = c(flow.astype(dtype), "convf1", 3)
  else:
    fx = jnp.pad(flow[..., 0], ((0, 0), (3, 3), (3, 3))).astype(dtype)
    taps = jnp.stack([fx[:, i:i + h, j:j + w] for i in range(7) for j in range(7)], axis=-1)
    flo = (taps @ p["convf1"]["kernel"][:, :, 0].reshape(49, -1).astype(dtype)
           + p["convf1"]["bias"].astype(dtype))
  flo = jax.nn.relu(c(jax.nn.relu(flo), "convf2", 1))
  out = jax.nn.relu(c(jnp.concatenate([cor, flo], axis=-1), "conv", 1))
  return jnp.concatenate([out, flow.astype(dtype)], axis=-1).reshape(*lead, h, w, -1)


def corr_path(pm, f1, f2, disp, maps_dtype, mlp_dtype):
  """Warp, 1x9 window correlation and correlation MLP with the maps and the MLP in the
  given dtypes (the model: both float32)."""
  warped = warp_x(f2.astype(maps_dtype), disp).astype(maps_dtype)
  corr = window_correlation(f1.astype(maps_dtype), warped, WIDE_WINDOW, 4)
  if mlp_dtype == jnp.float32:
    return CorrMLP().apply({"params": pm}, corr)
  fc = lambda y, n: y @ pm[n]["kernel"].astype(mlp_dtype) + pm[n]["bias"].astype(mlp_dtype)  # noqa: E731
  return fc(gelu(fc(corr.astype(mlp_dtype), "fc1")), "fc2").astype(jnp.float32)


def main():
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(ap)
  ap.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
  ap.add_argument("--skip-depth", action="store_true", help="leave out the depth-prior rows")
  a = ap.parse_args()
  dtype = jnp.dtype(a.dtype)
  cfg = sav_jax.SAVConfig(dtype=a.dtype)
  params = jax.device_put(init_variables(cfg, seed=0))["params"]
  ub = params["update_block"]
  lead = (1, a.frames, a.height // 4, a.width // 4)
  rng = np.random.default_rng(0)
  r = lambda c: jnp.asarray(rng.standard_normal((*lead, c)), dtype)  # noqa: E731
  h128, x256, n128 = r(128), r(256), r(128)
  gpu_bf16 = resolve_vit_attention("auto", dtype) == "cudnn"  # cuDNN's kernels apply
  rows = variant_rows(ub, h128, x256, n128, dtype, gpu_bf16)
  rows += motion_rows(ub["encoder"], r(1).astype(jnp.float32), r(128), dtype)
  n = lead[0] * lead[1]
  f1, f2 = (jnp.asarray(rng.standard_normal((n, *lead[2:], 128)), jnp.float32) for _ in "12")
  disp = jnp.asarray(rng.uniform(0, 8, (n, *lead[2:])), jnp.float32)
  rows += corr_rows(params["corr_mlp"], f1, f2, disp, dtype)
  if not a.skip_depth:
    frames = jnp.asarray(rng.uniform(0, 255, (2, a.frames, a.height, a.width, 3)), jnp.float32)
    for attention in ("blocked", "cudnn") if gpu_bf16 else ("blocked",):
      model = StereoAnyVideo(sav_jax.SAVConfig(dtype=a.dtype, vit_attention=attention))
      rows.append((f"depth prior, ViT attention {attention}",
                   lambda v, x, m=model: m.apply(v, x, method=lambda m, x: m.depthnet(x)),
                   ({"params": params}, frames), "depth"))
  print(f"T={a.frames} {a.height}x{a.width} (parts at 1/4: {lead[2]}x{lead[3]}) {a.dtype} "
        f"({jax.devices()[0].device_kind}, jax {jax.__version__})")
  ref = {}
  for label, fn, args, group in rows:
    f = jax.jit(fn)
    try:
      seconds = timed(f, *args)
    except Exception as e:  # pylint: disable=broad-except  # a variant the backend lacks
      print(f"  {label:40s} failed: {type(e).__name__}: {str(e).splitlines()[0][:100]}")
      continue
    out = np.asarray(f(*args), np.float32)
    diff = "" if group not in ref else f"  max diff {np.abs(out - ref[group]).max():.2e}"
    ref.setdefault(group, out)
    print(f"  {label:40s} {seconds * 1e3:8.2f} ms{diff}", flush=True)


def variant_rows(ub, h128, x256, n128, dtype, gpu_bf16=False):
  """`(label, fn, args, group)` rows: each group's first row is the model's module."""
  return [
      ("GRU (model)", lambda p, h, x: U.SKSepConvGRU3D(dtype=dtype).apply({"params": p}, h, x),
       (ub["gru"], h128, x256), "gru"),
      ("GRU z/r fused", lambda p, h, x: gru_fused(p, h, x, dtype), (ub["gru"], h128, x256), "gru"),
      ("flow head (model)", lambda p, n: U.FlowHead3D(dtype=dtype).apply({"params": p}, n),
       (ub["flow_head"], n128), "flow"),
      ("flow head native 3-D", lambda p, n: flow_head_native(p, n, dtype),
       (ub["flow_head"], n128), "flow"),
      ("flow head narrowing conv per tap", lambda p, n: flow_head_per_tap(p, n, dtype),
       (ub["flow_head"], n128), "flow"),
      ("space attention (model)", lambda p, x: U.SpaceAttnBlock(dtype=dtype).apply(
          {"params": p}, x), (ub["space_attn"], x256), "space"),
      ("space attention all frames at once", lambda p, x: space_attn_rewrite(p, x, dtype),
       (ub["space_attn"], x256), "space"),
      ("space attention q, k, v one product",
       lambda p, x: space_attn_rewrite(p, x, dtype, fused_qkv=True),
       (ub["space_attn"], x256), "space"),
      ("space attention per-head products",
       lambda p, x: space_attn_rewrite(p, x, dtype, attention=linear_attention_per_head),
       (ub["space_attn"], x256), "space"),
      ("time attention (model)", lambda p, x: U.TimeAttnBlock(dtype=dtype).apply(
          {"params": p}, x), (ub["time_attn"], x256), "time"),
      ("time attention dot_product_attention",
       lambda p, x: time_attn_dpa(p, x, dtype, "cudnn" if gpu_bf16 else "xla"),
       (ub["time_attn"], x256), "time"),
      ("time attention fused reductions", lambda p, x: time_attn_fused(p, x, dtype),
       (ub["time_attn"], x256), "time"),
      ("GRU split h/x convolutions", lambda p, h, x: gru_split(p, h, x, dtype),
       (ub["gru"], h128, x256), "gru"),
  ]


def motion_rows(p, flow, corr, dtype):
  """Rows of the motion encoder: the model's, then the 7x7 flow convolution's rewrites."""
  return [("motion encoder (model)", lambda p, f, c: U.BasicMotionEncoder(dtype).apply(
      {"params": p}, f, c), (p, flow, corr), "motion")] + [
          (f"motion encoder convf1 {mode}",
           lambda p, f, c, m=mode: motion_encoder_rewrite(p, f, c, dtype, m),
           (p, flow, corr), "motion") for mode in ("xy", "taps")]


def corr_rows(pm, f1, f2, disp, dtype):
  """Rows of warp + correlation + MLP: float32 (the model), then the compute dtype."""
  f32 = jnp.float32
  return [(f"warp+corr+MLP maps {jnp.dtype(md).name} MLP {jnp.dtype(ld).name}"
           + (" (model)" if md == f32 and ld == f32 else ""),
           lambda pm, a, b, d, md=md, ld=ld: corr_path(pm, a, b, d, md, ld),
           (pm, f1, f2, disp), "corr")
          for md, ld in dict.fromkeys(((f32, f32), (f32, dtype), (dtype, dtype)))]


if __name__ == "__main__":
  main()
