"""The correlation window schedule of the cascade: 1x9, 3x3, 1x9, ... restarting at each scale.

The official forward (models/core/stereoanyvideo.py) runs `for itr in range(iters // 2)` at
1/16 and at 1/8, then `for itr in range(iters)` at 1/4; each loop takes the 3x3 window
(`small_patch=True`) at odd `itr` and 1x9 otherwise, so the step counter starts at 0 in
every stage. The parity fixtures use iters=4 (2 + 2 + 4 steps, all even), where a counter
running on across stages picks the same windows; these tests watch which correlation the
compiled cascade runs when stages have odd lengths (as at iters=10, the paper's training
setting: 5 + 5 + 10 steps).
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from sav_jax.model import stereo_any_video as sav_module
from sav_jax.model.layers import CorrMLP
from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW

pytestmark = pytest.mark.usefixtures("fast_compile")

SIZE = (32, 48)  # frames H, W: 8x12 at 1/4, 4x6 at 1/8, 2x3 at 1/16
SCALES = ((2, 3), (4, 6), (8, 12))  # (h, w) of the 1/16, 1/8, 1/4 stages, in the cascade's order


def official_schedule(iters):
  """(scale, window) of every step of the official forward's three loops, in order."""
  window = lambda itr: SMALL_WINDOW if itr % 2 else WIDE_WINDOW  # noqa: E731
  steps = (iters // 2, iters // 2, iters)
  return [(hw, window(itr)) for hw, n in zip(SCALES, steps) for itr in range(n)]


class _LinearUpdate(nn.Module):
  """Stands in for SequenceUpdateBlock3D (same call and outputs): the delta is linear in the
  correlation features, the mask logits are zero. The window choice lives in
  `cascade`/`refine`/`step` and the correlation in `aapc`, which stay real; the real block
  made each cascade compile take 10-21 s instead of ~3 s (fast_compile, 2 shared cores)."""

  @nn.compact
  def __call__(self, net, inp, corr, flow, with_mask=True):
    delta = nn.Dense(2)(corr)
    return net, self.mask_logits(net) if with_mask else None, delta

  def mask_logits(self, net):
    return jnp.zeros((*net.shape[:-1], 27 * 4 * 4), jnp.float32)


class _CheapCascade(sav_jax.StereoAnyVideo):
  """The model's cascade, refine and step, with the light update block above."""

  def setup(self):
    self.corr_mlp = CorrMLP()
    self.update_block = _LinearUpdate()


@pytest.fixture(scope="module")
def cascade_inputs():
  rng = np.random.default_rng(0)
  shape = (1, 2, SIZE[0] // 4, SIZE[1] // 4, 128)  # B, T, h, w, C at 1/4
  feats = tuple(jnp.asarray(rng.standard_normal(shape, np.float32)) for _ in range(3))
  model = _CheapCascade()
  variables = jax.jit(lambda *f: model.init(jax.random.PRNGKey(0), *f, SIZE, 2, True,
                                            method=_CheapCascade.cascade))(*feats)
  return model, variables, feats


def run_recording_windows(monkeypatch, cascade_inputs, iters, final_only):
  """Runs the jitted cascade; returns the (scale, window) of every correlation that ran, in
  order, and the output.

  The model picks the window with `lax.cond` on a traced step index, so both correlations are
  traced (a trace-time record would list both): an ordered `jax.debug.callback` in each
  correlation fires only in the branch that executes.
  """
  model, variables, feats = cascade_inputs
  ran = []
  real_aapc = sav_module.aapc

  def recording_aapc(fmap1, fmap2, disp, window, groups=4):
    seen = (tuple(fmap1.shape[1:3]), tuple(window))
    jax.debug.callback(lambda: ran.append(seen), ordered=True)
    return real_aapc(fmap1, fmap2, disp, window, groups)

  monkeypatch.setattr(sav_module, "aapc", recording_aapc)
  run = jax.jit(lambda v, *f: model.apply(v, *f, SIZE, iters, final_only,
                                          method=_CheapCascade.cascade))
  out = jax.block_until_ready(run(variables, *feats))
  jax.effects_barrier()
  return ran, out


@pytest.mark.parametrize("iters,final_only", [(3, True), (3, False), (10, True)])
def test_window_alternation_restarts_at_every_scale(monkeypatch, cascade_inputs, iters,
                                                    final_only):
  # iters=3: 1 + 1 + 3 steps; iters=10: 5 + 5 + 10. A step counter carried on from stage to
  # stage would start the 1/8 stage with 3x3 in both. final_only=False (training: every
  # step upsampled) and True (inference) scan different step bodies. Each case compiles
  # one cascade: ~3.5 s with fast_compile on 2 shared CPU cores.
  ran, out = run_recording_windows(monkeypatch, cascade_inputs, iters, final_only)
  assert ran == official_schedule(iters)
  assert out.disparities.shape == (1 if final_only else 2 * (iters // 2) + iters, 1, 2, *SIZE)
