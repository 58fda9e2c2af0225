"""`SAVConfig`: the model's hyper-parameters (defaults = the paper's model, VDA-S)."""

from __future__ import annotations

import dataclasses
import inspect
import numbers
from typing import Optional

import numpy as np

# JAX is imported where it is used, so that importing this module (the CLI's `--help`, a
# training config file) does not import it.

# Default memory budget (MiB) of one block of frames of the per-frame stages
# (`SAVConfig.frame_block_mb`).
FRAME_BLOCK_MB = 1024.0

# Frames the depth prior's temporal attention takes at once (the length of its motion
# modules' sinusoidal table, `num_frames` of the official VideoDepthAnything): the longest
# clip or window the model runs.
TEMPORAL_MAX_LEN = 32

# Compute dtypes of the model (parameters stay float32).
DTYPES = ("float32", "bfloat16")
# Implementations of the depth prior's ViT attention (`SAVConfig.vit_attention`).
VIT_ATTENTION = ("auto", "blocked", "cudnn")
# Implementations of the GRU's wide (1x15) z/r convolutions (`SAVConfig.gru_conv`).
GRU_CONV = ("auto", "direct", "dft")


def resolve_gru_conv(choice: str, dtype) -> str:
  """The implementation `SAVConfig.gru_conv` stands for on JAX's default backend: "auto" is
  "dft" on CPU with float32 compute (there the 1x15 pair takes ~2x less time than XLA:CPU's
  convolutions, the forward ~12% less), else "direct" (GPUs: not measured; bfloat16: the
  DFT runs in float32)."""
  if choice != "auto":
    return choice
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  cpu = jax.default_backend() == "cpu"
  return "dft" if cpu and jnp.dtype(dtype) == jnp.float32 else "direct"


def resolve_vit_attention(choice: str, dtype) -> str:
  """The implementation `SAVConfig.vit_attention` stands for on JAX's default backend:
  "auto" is "cudnn" on an NVIDIA (CUDA) GPU backend of compute capability 8.0 or later
  (Ampere: cuDNN's fused attention kernels need it) with bfloat16 compute, else "blocked"
  (also on AMD GPUs, whose backend JAX calls "gpu" too, and on a V100 or T4)."""
  if choice != "auto":
    return choice
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  if jax.default_backend() != "gpu" or jnp.dtype(dtype) != jnp.bfloat16:
    return "blocked"
  device = jax.devices()[0]
  return "cudnn" if _cuda(device) and _ampere_or_later(device) else "blocked"


def _cuda(device) -> bool:
  """Whether a "gpu" device is an NVIDIA one (its client says "cuda ...", ROCm "rocm ...")."""
  try:
    return "rocm" not in str(device.client.platform_version).lower()
  except AttributeError:  # a client without the field: NVIDIA, JAX's usual GPU backend
    return True


def _ampere_or_later(device) -> bool:
  """Whether a CUDA device's compute capability (e.g. "9.0") is 8.0 or later; a device
  without the field (an older jaxlib) is taken to be."""
  capability = getattr(device, "compute_capability", None)
  if capability is None:
    return True
  try:
    return int(str(capability).split(".")[0]) >= 8
  except ValueError:
    return True

# Video Depth Anything encoder variants (DPT head width and per-level channels).
VDA_VARIANTS = {
    "vits": dict(features=64, out_channels=(48, 96, 192, 384)),
    "vitb": dict(features=128, out_channels=(96, 192, 384, 768)),
    "vitl": dict(features=256, out_channels=(256, 512, 1024, 1024)),
}


@dataclasses.dataclass(frozen=True)
class SAVConfig:
  """Stereo Any Video hyper-parameters.

  Attributes:
    vda_encoder: Video Depth Anything variant of the frozen depth prior: "vits" (the
      paper's and the official code's), "vitb" or "vitl", extensions with no official
      Stereo Any Video weights or counterpart (their heads' maps have 64 and 128 channels,
      which the 4x4 stride-4 conv takes in where the official conv takes 32).
    hidden_dim: GRU hidden channels (128 only).
    context_dim: context channels (depth 32 + cnet 96; 128 only).
    fnet_dim: channels of the fnet/cnet encoders' output.
    depth_dim: channels of the VDA feature map fed to the model.
    corr_groups: channel groups of the all-pairs correlation (a divisor of context_dim).
    upsample_rate: convex upsampling factor (1/4 -> 1; 4 only).
    dtype: compute dtype of convolutions, attention and the GRU ("float32" or
      "bfloat16"); parameters, correlation, attention logits and softmaxes, convex
      upsampling and the disparity accumulator stay float32.
    remat: rematerialise in the backward pass: each refinement step on its own, and the
      fnet/cnet encoders over blocks of frames sized for their backward (per frame,
      `model.stereo_any_video.ENCODER_BACKWARD_MAPS` times their largest map, under
      `frame_block_mb`).
      At the paper's training shape (B=1 T=5 256x512 iters=10) XLA:CPU's temporary
      memory is 4.2 GiB instead of 11.7 GiB before this covered the encoders and single
      steps (a step keeps one refinement step's activations, ~3.7 GiB, at its peak).
    remat_policy: name of a `jax.checkpoint_policies` policy for the refinement steps,
      or None for "save nothing"; only with `remat=True`.
    frame_block_mb: memory budget (MiB) of the per-frame stages' largest intermediate:
      the encoders, the depth prior's ViT attention logits and its full-resolution map
      run over blocks of frames (very large frames: of query rows) that fit it. Same
      values; bounds the memory of long, high-resolution windows. Not a weight setting.
      Training on several devices runs the model on each device's own clips
      (`train.step.per_device_apply`): a budget per device.
    vit_attention: the depth prior's ViT attention. "blocked" (every backend):
      `softmax(q k^T) v` in blocks under `frame_block_mb`. "cudnn": cuDNN's fused
      (flash) attention through `jax.nn.dot_product_attention`, which never stores the
      logits (at 720x1280 the ViT's 40 frames x 6 heads x 4642^2 logits per layer); CUDA
      GPUs and `dtype="bfloat16"` only (on an H200 it halves the depth prior's time at
      720x1280). "auto" (default): "cudnn" when JAX's default backend is an NVIDIA GPU
      of compute capability 8.0 or later (Ampere on) and `dtype="bfloat16"`, else "blocked"
      (`resolve_vit_attention`). Not a weight setting.
    gru_conv: the GRU's 1x15 z/r convolutions (the update block's widest). "direct":
      XLA's convolutions. "dft": both through one real DFT along the width, three real
      products per frequency bin instead of one per tap and pixel (`layers.dft_correlate_w`:
      ~5x fewer multiply-adds, the same values to float32 rounding, computed in float32).
      "auto" (default): "dft" on CPU with float32 compute, else "direct"
      (`resolve_gru_conv`). Not a weight setting.
    detach_flow: stop the gradient of the flow entering each refinement step, as the
      official model (`flow.detach()`, RAFT's truncated backpropagation; training uses it).
      Values are the same either way; False gives the true derivative of the predictions
      with respect to the frames and the parameters (with True, d(final disparity)/d(frames)
      leaves out every path through the earlier steps' flows, and can have the other sign),
      for pipelines that differentiate the output itself, e.g. a photometric loss.
  """

  vda_encoder: str = "vits"
  hidden_dim: int = 128
  context_dim: int = 128
  fnet_dim: int = 96
  depth_dim: int = 32
  corr_groups: int = 4
  upsample_rate: int = 4
  dtype: str = "float32"
  remat: bool = False
  remat_policy: Optional[str] = None
  frame_block_mb: float = FRAME_BLOCK_MB
  vit_attention: str = "auto"
  gru_conv: str = "auto"
  detach_flow: bool = True

  def __post_init__(self):
    if self.dtype is not None and not isinstance(self.dtype, str):  # jnp.bfloat16: as predict_video
      try:
        object.__setattr__(self, "dtype", np.dtype(self.dtype).name)
      except TypeError:
        pass  # named below
    for f in dataclasses.fields(self):  # numpy scalars become Python values (hash, JSON)
      object.__setattr__(self, f.name, _checked_value(f.name, getattr(self, f.name), f.type))
    if self.remat_policy is not None and self.remat_policy not in remat_policies():
      raise ValueError(f"SAVConfig.remat_policy={self.remat_policy!r}; expected None or one of "
                       f"{remat_policies()} (jax.checkpoint_policies)")
    if self.remat_policy is not None and not self.remat:
      raise ValueError(f"SAVConfig.remat_policy={self.remat_policy!r} has no effect with "
                       "remat=False: set remat=True too, or leave the policy None")
    if self.vda_encoder not in VDA_VARIANTS:
      raise ValueError(
          f"SAVConfig.vda_encoder={self.vda_encoder!r}; expected one of {sorted(VDA_VARIANTS)}")
    if self.dtype not in DTYPES:
      raise ValueError(f"SAVConfig.dtype={self.dtype!r}; expected 'float32' or 'bfloat16'")
    if not 0 < self.frame_block_mb < float("inf"):
      raise ValueError(f"SAVConfig.frame_block_mb must be a finite number > 0, got "
                       f"{self.frame_block_mb!r}")
    if self.vit_attention not in VIT_ATTENTION:
      raise ValueError(f"SAVConfig.vit_attention={self.vit_attention!r}; expected one of "
                       f"{VIT_ATTENTION}")
    if self.vit_attention == "cudnn" and self.dtype != "bfloat16":
      raise ValueError("SAVConfig.vit_attention='cudnn' needs dtype='bfloat16' (cuDNN's fused "
                       f"attention has no float32 kernels), got dtype={self.dtype!r}")
    if self.gru_conv not in GRU_CONV:
      raise ValueError(f"SAVConfig.gru_conv={self.gru_conv!r}; expected one of {GRU_CONV}")
    if self.depth_dim + self.fnet_dim != self.context_dim:
      raise ValueError(
          f"depth_dim + fnet_dim must equal context_dim ({self.depth_dim} + {self.fnet_dim} "
          f"!= {self.context_dim})")
    # The update block's layer widths are the official ones (its attention runs on 256 =
    # 128 context + 128 motion channels, its GRU on 128): these three are fixed.
    for name, value in (("hidden_dim", 128), ("context_dim", 128), ("upsample_rate", 4)):
      if getattr(self, name) != value:
        raise ValueError(f"SAVConfig.{name}={getattr(self, name)!r}: the model supports only "
                         f"{value} (the official architecture)")
    if self.corr_groups < 1 or self.context_dim % self.corr_groups:
      raise ValueError(f"SAVConfig.corr_groups={self.corr_groups!r} must divide the "
                       f"{self.context_dim} feature channels of the correlation")

  @property
  def compute_dtype(self):
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    return jnp.bfloat16 if self.dtype == "bfloat16" else jnp.float32

  @property
  def vda(self) -> dict:
    return dict(encoder=self.vda_encoder, **VDA_VARIANTS[self.vda_encoder])

  def to_dict(self) -> dict:
    return dataclasses.asdict(self)

  @classmethod
  def from_dict(cls, d: dict) -> "SAVConfig":
    if not hasattr(d, "keys"):  # any mapping: dict, ConfigDict, FrozenDict, ...
      raise ValueError(f"a SAVConfig mapping is expected, got {type(d).__name__}: {d!r:.100}")
    d = {k: d[k] for k in d.keys()}
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
      raise ValueError(f"unknown SAVConfig fields {unknown}; known: {sorted(names)}")
    return cls(**d)


def _checked_value(name: str, value, annotation: str):
  """`value` of field `name` as the Python type of its annotation (numpy scalars included;
  ints are not bools, floats accept ints); a ValueError naming the field otherwise."""
  kinds = {"str": str, "Optional[str]": str, "int": numbers.Integral, "float": numbers.Real,
           "bool": (bool, np.bool_)}
  assert annotation in kinds, f"SAVConfig.{name}: add its annotation {annotation!r} here"
  if value is None and annotation.startswith("Optional["):
    return None
  is_bool = isinstance(value, (bool, np.bool_))
  if not isinstance(value, kinds[annotation]) or (is_bool and annotation in ("int", "float")):
    kind = type(value)
    named = _policy_name(value) if name == "remat_policy" else None
    hint = f" (the name {named}, not the policy)" if named else ""
    raise ValueError(f"SAVConfig.{name}={value!r} ({kind.__module__}.{kind.__qualname__}); "
                     f"expected {annotation}{hint}")
  value = {"int": int, "float": float, "bool": bool}.get(annotation, str)(value)
  if annotation == "int" and value < 1:
    raise ValueError(f"SAVConfig.{name} must be >= 1, got {value!r}")
  return value


def _policy_name(policy) -> str | None:
  """The names in `jax.checkpoint_policies` of `policy` (a policy given for its name), e.g.
  "'checkpoint_dots' or 'dots_saveable'" (aliases), or None."""
  import jax  # pylint: disable=import-outside-toplevel
  names = [repr(n) for n in remat_policies() if getattr(jax.checkpoint_policies, n) is policy]
  return " or ".join(names) or None


def remat_policies() -> list[str]:
  """Names usable as `SAVConfig.remat_policy`: the `jax.checkpoint_policies` that are policies
  themselves (called as `policy(prim, *args, **params)`), not factories of policies such as
  `save_only_these_names(*names)`."""
  import jax  # pylint: disable=import-outside-toplevel
  def is_policy(fn):
    try:
      params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
      return False
    return any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
  return sorted(k for k, v in vars(jax.checkpoint_policies).items()
                if not k.startswith("_") and callable(v) and is_policy(v))


def as_config(cfg, where: str = "cfg", allow_none: bool = True) -> "SAVConfig":
  """`cfg`, or the paper's model for None (where `allow_none`).

  Raises:
    TypeError: `cfg` is not a `SAVConfig` (a dict of its fields: `SAVConfig.from_dict(d)`).
  """
  if cfg is None and allow_none:
    return SAVConfig()
  if not isinstance(cfg, SAVConfig):
    raise TypeError(f"{where} must be a sav_jax.SAVConfig (SAVConfig.from_dict(d) for a dict), "
                    f"got {type(cfg).__name__}")
  return cfg
