"""Memory blocking of per-frame stages: same values as the single computation."""

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from sav_jax.model import depth, dinov2, dpt_temporal, stereo_any_video, update
from sav_jax.model.dinov2 import (DinoVisionTransformer, attention_blocks, fused_attention,
                                  softmax_attention)
from sav_jax.model.layers import frames_per_block

# Blocked and single computations compared: no need for XLA's optimisations.
pytestmark = pytest.mark.usefixtures("fast_compile")


def test_attention_blocks_choose_frames_then_query_rows():
  per_frame_mb = 6 * 100 * 100 * 4 / 2**20
  assert attention_blocks(8, 6, 100, 8 * per_frame_mb) == (8, 100)  # all fits: one block
  assert attention_blocks(8, 6, 100, 5 * per_frame_mb) == (4, 100)  # largest divisor <= 5
  assert attention_blocks(7, 6, 100, 5 * per_frame_mb) == (1, 100)  # 7 is prime
  assert attention_blocks(8, 6, 100, per_frame_mb / 4) == (1, 25)  # query rows
  assert attention_blocks(8, 6, 100, 1e-9) == (1, 1)


@pytest.mark.parametrize("budget_rows", [None, 2, 7])  # frames blocked / rows 2 / rows 7 (padded)
def test_blocked_softmax_attention_equals_the_single_product(budget_rows):
  rng = np.random.default_rng(0)
  n, length, heads, d = 6, 50, 3, 8
  q, k, v = (jnp.asarray(rng.standard_normal((n, length, heads, d)), jnp.float32)
             for _ in range(3))
  want = softmax_attention(q, k, v, budget_mb=1e6)
  per_row_mb = heads * length * 4 / 2**20
  budget = 2 * length * per_row_mb if budget_rows is None else budget_rows * per_row_mb
  frames, rows = attention_blocks(n, heads, length, budget)
  assert (frames, rows) == ((2, length) if budget_rows is None else (1, budget_rows))
  got = jax.jit(lambda q, k, v: softmax_attention(q, k, v, budget))(q, k, v)
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
  # the loops run over blocks of that size: n / frames blocks, or frames then row blocks
  jaxpr = jax.make_jaxpr(lambda q, k, v: softmax_attention(q, k, v, budget))(q, k, v).jaxpr
  assert _scan_lengths(jaxpr) == ([n // frames] if rows == length else [n, -(-length // rows)])


def _scan_lengths(jaxpr) -> list[int]:
  """The lengths of the scans (`lax.map`s) in `jaxpr`, outer ones first."""
  lengths = []
  for eqn in jaxpr.eqns:
    if eqn.primitive.name == "scan":
      lengths.append(eqn.params["length"])
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      lengths += _scan_lengths(sub)
  return lengths


@pytest.mark.parametrize("dtype,tol", [(jnp.float32, 1e-5), (jnp.bfloat16, 2e-2)])
def test_fused_attention_takes_the_blocked_layout_and_scaling(dtype, tol):
  """`fused_attention` (the cuDNN option's call, here through JAX's reference "xla" path)
  computes what `softmax_attention` does from the same `[N, L, heads, d]` pre-scaled inputs."""
  rng = np.random.default_rng(1)
  q, k, v = (jnp.asarray(rng.standard_normal((2, 37, 3, 8)), dtype) for _ in range(3))
  q = q * 8**-0.5
  got = fused_attention(q, k, v, "xla")
  want = softmax_attention(q, k, v, budget_mb=1e-4)  # query-row blocks
  assert got.dtype == dtype and got.shape == want.shape
  np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(want, np.float32),
                             rtol=tol, atol=tol)


def test_cudnn_vit_attention_is_checked_with_clear_errors():
  with pytest.raises(ValueError, match="vit_attention='cudnn' needs dtype='bfloat16'"):
    sav_jax.SAVConfig(vit_attention="cudnn")
  with pytest.raises(ValueError, match="vit_attention='flash'; expected one of"):
    sav_jax.SAVConfig(vit_attention="flash")
  cfg = sav_jax.SAVConfig(dtype="bfloat16", vit_attention="cudnn")
  model = sav_jax.StereoAnyVideo(cfg)
  assert model.cfg.vit_attention == "cudnn"
  if jax.default_backend() != "gpu":  # the CI case: no CUDA device, a message, not a traceback
    vit = DinoVisionTransformer(depth=1, layers=(0,), dtype=jnp.bfloat16, attention="cudnn")
    with pytest.raises(ValueError, match="needs a CUDA GPU"):
      jax.eval_shape(vit.init, jax.random.key(0), jnp.zeros((1, 28, 28, 3)))
    # the model's depth prior takes the config's choice (not its own default, "blocked")
    video = jnp.zeros((1, 1, 32, 32, 3))
    with pytest.raises(ValueError, match="needs a CUDA GPU"):
      jax.eval_shape(lambda: model.init(jax.random.key(0), video, video, iters=2))


def test_auto_vit_attention_runs_the_fused_kernel_where_it_resolves_to_cudnn(monkeypatch):
  """The ViT's attention resolves "auto" itself: on a (faked) Ampere CUDA GPU in bfloat16 it
  calls the fused kernel, in float32 the blocked softmax; the fused kernel refuses float32."""
  device = type("Device", (), {"client": type("Client", (), {"platform_version": "cuda 12080"})(),
                               "compute_capability": "9.0"})()
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(jax, "devices", lambda *a: [device])
  with pytest.raises(ValueError, match="needs bfloat16 compute, got float32"):
    fused_attention(*[jnp.zeros((1, 4, 2, 8), jnp.float32)] * 3, "cudnn")
  calls = []
  monkeypatch.setattr(dinov2, "fused_attention",
                      lambda q, k, v, impl: calls.append(impl) or softmax_attention(q, k, v))
  x = jnp.zeros((1, 5, 16))
  for dtype, want in ((jnp.bfloat16, ["cudnn"]), (jnp.float32, [])):
    calls.clear()
    jax.eval_shape(dinov2.Attention(2, dtype, implementation="auto").init, jax.random.key(0), x)
    assert calls == want, dtype


def test_frame_block_mb_reaches_every_blocked_stage(monkeypatch):
  """`frame_block_mb` bounds every per-frame stage of the model: the ViT attention's logits
  (every layer's), the depth head's full-resolution end (blocked by its float32 map, H x W x
  32 channels for vits: 118 MB a frame at 720x1280), the fnet/cnet encoders, the update
  block's space attention and its GRU's DFT spectra."""
  seen = {}

  def record(module, name, budget_of):
    original = getattr(module, name)

    def wrapper(*args):
      seen.setdefault(f"{module.__name__.rsplit('.', 1)[-1]}.{name}", set()).add(budget_of(args))
      return original(*args)

    monkeypatch.setattr(module, name, wrapper)

  record(dinov2, "softmax_attention", lambda a: a[3])
  record(depth, "in_frame_blocks", lambda a: (a[2].shape[0], a[3], a[4]))
  record(stereo_any_video, "in_frame_blocks", lambda a: a[4])
  record(update, "in_frame_blocks", lambda a: a[4])
  record(update, "dft_correlate_w", lambda a: a[2])
  model = sav_jax.StereoAnyVideo(sav_jax.SAVConfig(frame_block_mb=3.0, gru_conv="dft"))
  video = jnp.zeros((1, 2, 32, 48, 3))
  jax.eval_shape(lambda: model.init(jax.random.key(0), video, video, iters=2))
  assert seen == {"dinov2.softmax_attention": {3.0},
                  "depth.in_frame_blocks": {(2 * 2, 32 * 48 * 32 * 4, 3.0)},  # both views
                  "stereo_any_video.in_frame_blocks": {3.0},
                  "update.in_frame_blocks": {3.0}, "update.dft_correlate_w": {3.0}}


def test_gru_dft_runs_in_blocks_under_its_budget():
  """With the DFT's 1x15 gates, `block_mb` splits their spectra into blocks of rows (more,
  smaller products; values as tests/model/test_layers.py checks), where the default budget
  takes all rows at once."""
  from sav_jax.model.update import SKSepConvGRU3D  # pylint: disable=import-outside-toplevel
  h, x = jnp.zeros((1, 2, 4, 8, 128)), jnp.zeros((1, 2, 4, 8, 256))

  def dots(**kwargs):
    gru = SKSepConvGRU3D(wide_conv="dft", **kwargs)
    variables = jax.eval_shape(gru.init, jax.random.key(0), h, x)
    return str(jax.make_jaxpr(gru.apply)(variables, h, x)).count("dot_general")

  assert dots(block_mb=1e-3) > dots()


def test_auto_vit_attention_picks_cudnn_only_on_a_gpu_in_bfloat16(monkeypatch):
  from sav_jax.config import resolve_vit_attention  # pylint: disable=import-outside-toplevel
  assert sav_jax.SAVConfig().vit_attention == "auto"
  assert resolve_vit_attention("blocked", jnp.bfloat16) == "blocked"
  assert resolve_vit_attention("cudnn", jnp.bfloat16) == "cudnn"
  backend = jax.default_backend()
  assert resolve_vit_attention("auto", jnp.bfloat16) == (
      "cudnn" if backend == "gpu" else "blocked")
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  assert resolve_vit_attention("auto", jnp.bfloat16) == "cudnn"
  assert resolve_vit_attention("auto", "bfloat16") == "cudnn"
  assert resolve_vit_attention("auto", jnp.float32) == "blocked"
  # JAX calls AMD's backend "gpu" too: cuDNN only where the client is CUDA's.
  for version, want in (("rocm 60200", "blocked"), ("cuda 12040", "cudnn")):
    fake = type("Device", (), {"client": type("Client", (), {"platform_version": version})()})()
    monkeypatch.setattr(jax, "devices", lambda *a, d=fake: [d])
    assert resolve_vit_attention("auto", jnp.bfloat16) == want, version
  # a client or a compute capability this code cannot read: JAX's usual GPU, NVIDIA's
  monkeypatch.setattr(jax, "devices", lambda *a: [type("Device", (), {})()])
  assert resolve_vit_attention("auto", jnp.bfloat16) == "cudnn"
  # cuDNN's fused attention for arbitrary sequence lengths needs Ampere (8.0) or later (as
  # NVIDIA's Transformer Engine selects it): "auto" chose it on a T4 (7.5) or V100 (7.0) too.
  for capability, want in (("7.0", "blocked"), ("7.5", "blocked"), ("8.0", "cudnn"),
                           ("8.6", "cudnn"), ("9.0", "cudnn"), ("10.0", "cudnn"),
                           ("sm_90", "cudnn")):
    fake = type("Device", (), {"client": type("Client", (), {"platform_version": "cuda 12080"})(),
                               "compute_capability": capability})()
    monkeypatch.setattr(jax, "devices", lambda *a, d=fake: [d])
    assert resolve_vit_attention("auto", jnp.bfloat16) == want, capability
  monkeypatch.undo()
  monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
  assert resolve_vit_attention("auto", jnp.bfloat16) == "blocked"
  # The default model traces the blocked path here (no dot_product_attention call).
  vit = DinoVisionTransformer(depth=1, layers=(0,), dtype=jnp.bfloat16, attention="auto")
  jaxpr = str(jax.make_jaxpr(lambda x: vit.init(jax.random.key(0), x))(jnp.zeros((1, 28, 28, 3))))
  assert "dot_product_attention" not in jaxpr and "cudnn" not in jaxpr


def test_gru_conv_is_checked_and_auto_picks_the_dft_on_a_cpu_in_float32(monkeypatch):
  from sav_jax.config import resolve_gru_conv  # pylint: disable=import-outside-toplevel
  from sav_jax.model.update import SKSepConvGRU3D  # pylint: disable=import-outside-toplevel
  assert sav_jax.SAVConfig().gru_conv == "auto"
  with pytest.raises(ValueError, match="gru_conv='fft'; expected one of"):
    sav_jax.SAVConfig(gru_conv="fft")
  with pytest.raises(ValueError, match=r"wide_conv='fft'; expected one of \('auto', 'direct'"):
    h, x = jnp.zeros((1, 1, 2, 4, 128)), jnp.zeros((1, 1, 2, 4, 256))
    jax.eval_shape(SKSepConvGRU3D(wide_conv="fft").init, jax.random.key(0), h, x)
  for choice in ("direct", "dft"):  # explicit choices hold everywhere
    assert resolve_gru_conv(choice, jnp.bfloat16) == choice
  monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
  assert resolve_gru_conv("auto", jnp.float32) == "dft"
  assert resolve_gru_conv("auto", "float32") == "dft"
  assert resolve_gru_conv("auto", jnp.bfloat16) == "direct"
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # not measured there
  assert resolve_gru_conv("auto", jnp.float32) == "direct"
  # The model builds its GRU with the resolved choice (the DFT's products in its program).
  monkeypatch.undo()
  seen = []
  monkeypatch.setattr(SKSepConvGRU3D, "__call__",
                      lambda self, h, x: seen.append(self.wide_conv) or h)
  video = jnp.zeros((1, 2, 64, 64, 3))
  for choice in ("direct", "dft"):
    model = sav_jax.StereoAnyVideo(sav_jax.SAVConfig(gru_conv=choice))
    seen.clear()
    jax.eval_shape(lambda m=model: m.init(jax.random.key(0), video, video, iters=2))
    assert seen and set(seen) == {choice}


def test_frames_per_block_is_a_divisor_within_the_budget():
  assert frames_per_block(40, 2**20, 10) == 10
  assert frames_per_block(40, 2**20, 7) == 5
  assert frames_per_block(40, 2**30, 1) == 1  # one frame even over the budget
  assert frames_per_block(3, 1, 1) == 3


def test_frame_block_budget_must_be_positive():
  with pytest.raises(ValueError, match="frame_block_mb"):
    sav_jax.SAVConfig(frame_block_mb=0)


def test_blocked_space_attention_has_the_same_values_and_gradients():
  """Blocks of frames (`nn.scan` over frames, shared parameters) train like the single pass."""
  from sav_jax.model.update import SpaceAttnBlock  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.standard_normal((1, 4, 3, 5, 16)), jnp.float32)
  whole = SpaceAttnBlock(16)
  blocked = SpaceAttnBlock(16, block_mb=2 * 15 * 2 * 16 * 4 / 2**20)  # two frames per block
  variables = whole.init(jax.random.key(0), x)
  assert jax.tree.structure(blocked.init(jax.random.key(0), x)) == jax.tree.structure(variables)

  def loss(mdl):
    return lambda v, x: jnp.sum(jnp.sin(mdl.apply(v, x)))

  np.testing.assert_allclose(blocked.apply(variables, x), whole.apply(variables, x),
                             rtol=1e-5, atol=1e-5)
  got = jax.grad(loss(blocked), argnums=(0, 1))(variables, x)
  want = jax.grad(loss(whole), argnums=(0, 1))(variables, x)
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
  assert "scan[" in str(jax.make_jaxpr(lambda v, x: blocked.apply(v, x))(variables, x))


@pytest.mark.parametrize("dtype,tol", [(jnp.float32, 1e-5), (jnp.bfloat16, 3e-2)])
def test_linear_attention_keeps_the_heads_apart(dtype, tol):
  """The heads' products taken as one block-diagonal product give LoFTR's per-head linear
  attention (queries and keys of different lengths, value width != key width)."""
  from sav_jax.model.update import linear_attention  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(2)
  q, k, v = (rng.standard_normal(s) for s in ((2, 7, 3, 4), (2, 5, 3, 4), (2, 5, 3, 6)))
  fq, fk = (np.where(a > 0, a + 1, np.exp(a)) for a in (q, k))  # elu(a) + 1
  want = np.zeros((2, 7, 3, 6))
  for n in range(2):
    for h in range(3):
      num = fq[n, :, h] @ (fk[n, :, h].T @ v[n, :, h])
      want[n, :, h] = num / (fq[n, :, h] @ fk[n, :, h].sum(axis=0) + 1e-6)[:, None]
  got = linear_attention(*(jnp.asarray(a, dtype) for a in (q, k, v)))
  assert got.shape == want.shape and got.dtype == dtype
  np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=tol, atol=tol)


def _bf16_dots_into_float32(jaxpr) -> int:
  """dot_generals of bfloat16 operands whose result is float32, anywhere in `jaxpr`."""
  count = 0
  for eqn in jaxpr.eqns:
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      count += _bf16_dots_into_float32(sub)
    if (eqn.primitive.name == "dot_general"
        and all(v.aval.dtype == jnp.bfloat16 for v in eqn.invars)
        and eqn.outvars[0].aval.dtype == jnp.float32):
      count += 1
  return count


def test_bfloat16_attention_logits_stay_float32():
  # Logits 300 and 301 (bfloat16 has 8 bits: 301 would round to 300 or 302 before the
  # float32 softmax): the weights must be softmax([300, 301]) = (0.269, 0.731).
  q = jnp.asarray([[[[1.0, 1.0]]]], jnp.bfloat16)  # [N=1, L=1, heads=1, d=2]
  k = jnp.asarray([[[[150.0, 150.0]]], [[[150.0, 151.0]]]], jnp.bfloat16).reshape(1, 2, 1, 2)
  v = jnp.asarray([[0.0, 0.0], [1.0, 1.0]], jnp.bfloat16).reshape(1, 2, 1, 2)
  out = dinov2.softmax_attention(q, k, v)
  np.testing.assert_allclose(np.asarray(out, np.float32)[0, 0, 0], [0.731] * 2, atol=4e-3)
  # the motion modules' attention across frames too
  module = dpt_temporal.TemporalAttention(heads=1, dtype=jnp.bfloat16)
  x = jnp.zeros((1, 3, 2, 8), jnp.bfloat16)
  variables = jax.eval_shape(module.init, jax.random.PRNGKey(0), x)
  jaxpr = jax.make_jaxpr(module.apply)(variables, x).jaxpr
  assert _bf16_dots_into_float32(jaxpr) >= 1
