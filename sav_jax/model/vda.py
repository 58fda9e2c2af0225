"""Video Depth Anything (frozen depth prior of SAV): DINOv2 + temporal DPT head.

Reproduces the vendored `VideoDepthAnything.forward` of Stereo Any Video: the
DPT head stops after `output_conv1` and its align_corners=True resize to the
input size, so the model returns 32-channel features, not depth. Channels last.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from sav_jax.config import FRAME_BLOCK_MB
from sav_jax.model.dinov2 import DINO_VARIANTS, DinoVisionTransformer
from sav_jax.model.dpt_temporal import TEMPORAL_MAX_LEN, DPTHeadTemporal

PATCH_SIZE = 14


class VideoDepthAnything(nn.Module):
  """VDA encoder + temporal DPT head, up to the 32-channel feature map.

  Attributes:
    encoder: DINOv2 variant ("vits", "vitb", "vitl").
    features: width of the DPT fusion path (64 for vits).
    out_channels: widths of the four projected ViT layers.
    dtype: compute dtype; parameters are float32.
    attention_block_mb: memory budget of one block of the ViT's attention logits
      (`dinov2.softmax_attention`).
    attention: the ViT attention's implementation ("blocked", "cudnn" or "auto",
      `SAVConfig.vit_attention`).
  """

  encoder: str = "vits"
  features: int = 64
  out_channels: tuple = (48, 96, 192, 384)
  dtype: Any = jnp.float32
  attention_block_mb: float = FRAME_BLOCK_MB
  attention: str = "blocked"

  def setup(self):
    if self.encoder not in DINO_VARIANTS:
      raise ValueError(f"unknown VDA encoder {self.encoder!r}; expected one of "
                       f"{sorted(DINO_VARIANTS)}")
    self.pretrained = DinoVisionTransformer(**DINO_VARIANTS[self.encoder],
                                            patch_size=PATCH_SIZE, dtype=self.dtype,
                                            attention_block_mb=self.attention_block_mb,
                                            attention=self.attention)
    self.head = DPTHeadTemporal(self.features, tuple(self.out_channels),
                                max_len=TEMPORAL_MAX_LEN, dtype=self.dtype)

  def intermediates(self, x: jax.Array) -> dict[str, Any]:
    """Runs the model and returns its intermediate values as well.

    Args:
      x: `[B, T, H14, W14, 3]` ImageNet-normalised frames, sides multiples of 14.

    Returns:
      dict with
        "pos_embed": `[1, 1 + h*w, D]` interpolated DINOv2 position table (float32),
        "patch": list of four `[B*T, h*w, D]` normalised patch tokens (b-major),
        "cls": list of four `[B*T, D]` normalised class tokens,
        "head": `[B, T, H14, W14, features // 2]` the output of `__call__`.
    """
    b, t, height, width, c = x.shape
    if c != 3:
      raise ValueError(f"expected RGB frames [B, T, H, W, 3], got {x.shape}")
    if height % PATCH_SIZE or width % PATCH_SIZE:
      raise ValueError(f"VDA input sides must be multiples of {PATCH_SIZE}, got {height}x{width}")
    if t > TEMPORAL_MAX_LEN:
      raise ValueError(f"VDA processes at most {TEMPORAL_MAX_LEN} frames at once, got {t}")
    grid = (height // PATCH_SIZE, width // PATCH_SIZE)
    layers, pos_embed = self.pretrained(x.reshape(b * t, height, width, c).astype(self.dtype))
    out = self.head([p for p, _ in layers], grid, t)
    return {
        "pos_embed": pos_embed,
        "patch": [p for p, _ in layers],
        "cls": [cl for _, cl in layers],
        "head": out.reshape(b, t, *out.shape[1:]),
    }

  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H14, W14, 3]` normalised. Returns `[B, T, H14, W14, features // 2]`."""
    return self.intermediates(x)["head"]

  def tokens(self, x: jax.Array) -> list[jax.Array]:
    """The per-frame part: DINOv2's four normalised patch-token maps.

    Args:
      x: `[N, H14, W14, 3]` normalised frames (any frames: nothing mixes them here).

    Returns:
      Four `[N, h*w, D]` arrays, the input of `head_from_tokens`.
    """
    if x.ndim != 4 or x.shape[-1] != 3:
      raise ValueError(f"expected RGB frames [N, H, W, 3], got {x.shape}")
    if x.shape[1] % PATCH_SIZE or x.shape[2] % PATCH_SIZE:
      raise ValueError(f"VDA input sides must be multiples of {PATCH_SIZE}, got {x.shape[1:3]}")
    layers, _ = self.pretrained(x.astype(self.dtype))
    return [p for p, _ in layers]

  def head_from_tokens(self, tokens: list[jax.Array], grid: tuple[int, int], b: int,
                       t: int, resize_output: bool = True) -> jax.Array:
    """The temporal part: the DPT head over the `t` frames of each of `b` clips.

    Args:
      tokens: four `[b*t, h*w, D]` arrays (clip-major) from `tokens`.
      grid: `(h, w)` patch grid.
      b, t: clips and frames per clip.
      resize_output: see `DPTHeadTemporal.__call__`.

    Returns:
      `[b, t, 14h, 14w, features // 2]`, as `__call__` (`8h, 8w` without the resize).
    """
    if t > TEMPORAL_MAX_LEN:
      raise ValueError(f"VDA processes at most {TEMPORAL_MAX_LEN} frames at once, got {t}")
    out = self.head(list(tokens), grid, t, resize_output)
    return out.reshape(b, t, *out.shape[1:])
