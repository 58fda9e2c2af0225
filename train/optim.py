"""Optimizer of the official trainer: AdamW + OneCycle (linear), clipping, frozen depth prior.

Official (`train_stereoanyvideo.py: fetch_optimizer`): `AdamW(lr, weight_decay=wdecay,
eps=1e-8)` with PyTorch's default betas, `OneCycleLR(max_lr=lr, total_steps=num_steps +
100, pct_start=0.01, cycle_momentum=False, anneal_strategy="linear")` with the default
`div_factor=25` and `final_div_factor=1e4`, `clip_grad_norm_(params, 1.0)` before every
step, and every parameter whose name contains `depthanything` frozen
(`requires_grad_(False)`: no update, no optimizer state, not in the clipping norm).
"""

from __future__ import annotations

import re
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax

FROZEN = "frozen"
TRAINABLE = "trainable"


def one_cycle_linear(max_lr: float, total_steps: int, pct_start: float = 0.01,
                     div_factor: float = 25.0, final_div_factor: float = 1e4,
                     stop_at: int | None = None) -> Callable[[Any], jax.Array]:
  """PyTorch `OneCycleLR(anneal_strategy="linear", three_phase=False)` as an optax schedule.

  Args:
    max_lr: peak learning rate.
    total_steps: the scheduler's `total_steps`.
    pct_start: fraction of `total_steps` spent warming up.
    div_factor: initial lr = max_lr / div_factor.
    final_div_factor: final lr = initial lr / final_div_factor.
    stop_at: the official loop stops stepping the scheduler at `num_steps`, so the lr
      of later updates stays at the value of update `stop_at` (None: no stop).

  Returns:
    `schedule(count) -> lr` (float32), where `count` is the number of updates done.
  """
  initial = max_lr / div_factor
  final = initial / final_div_factor
  warm_end = float(pct_start * total_steps) - 1.0
  last = float(total_steps - 1)
  if warm_end <= 0 or last <= warm_end:
    raise ValueError(f"degenerate one-cycle schedule: total_steps={total_steps}, "
                     f"pct_start={pct_start}")

  def schedule(count):
    s = jnp.asarray(count, jnp.float32)
    if stop_at is not None:
      s = jnp.minimum(s, float(stop_at))
    up = initial + (max_lr - initial) * (s / warm_end)
    # = max_lr + (final - max_lr) * (s - warm_end) / (last - warm_end), without the
    # float32 cancellation near the end.
    down = final + (max_lr - final) * ((last - s) / (last - warm_end))
    return jnp.where(s <= warm_end, up, down).astype(jnp.float32)

  return schedule


def param_labels(params, frozen_pattern: str):
  """`"frozen"` for leaves whose `/`-joined path matches `frozen_pattern`, else `"trainable"`.

  Args:
    params: parameter pytree (nested dicts).
    frozen_pattern: regular expression searched in paths like
      `depthnet/depthanything/pretrained/blocks_0/attn/qkv/kernel`; empty = nothing frozen.

  Returns:
    A pytree of labels with the structure of `params`.
  """
  regex = re.compile(frozen_pattern) if frozen_pattern else None

  def label(path, _):
    name = "/".join(str(getattr(k, "key", getattr(k, "name", k))) for k in path)
    return FROZEN if regex is not None and regex.search(name) else TRAINABLE

  return jax.tree_util.tree_map_with_path(label, params)


def make_schedule(opt_cfg, num_steps: int) -> Callable[[Any], jax.Array]:
  """The learning-rate schedule of an optimizer config (see `configs/sceneflow.py`)."""
  if opt_cfg.schedule == "constant":
    return optax.constant_schedule(opt_cfg.lr)
  if opt_cfg.schedule != "one_cycle":
    raise ValueError(f"unknown schedule {opt_cfg.schedule!r}; expected 'one_cycle' or 'constant'")
  total = opt_cfg.schedule_steps if opt_cfg.schedule_steps > 0 else num_steps + 100
  # The official loop stops the scheduler at num_steps, before the cycle ends (total is
  # num_steps + 100). A cycle set shorter than the run (`schedule_steps`) holds its final
  # lr afterwards instead of extrapolating the linear decay below zero.
  return one_cycle_linear(opt_cfg.lr, total, opt_cfg.pct_start, opt_cfg.div_factor,
                          opt_cfg.final_div_factor, stop_at=total - 1)


def make_optimizer(opt_cfg, num_steps: int, params) -> optax.GradientTransformation:
  """Clip + AdamW on the trainable leaves, nothing (no state) on the frozen ones.

  Args:
    opt_cfg: the `optimizer` block of a config.
    num_steps: training length (sets the one-cycle length as the official script).
    params: parameter pytree or its `jax.eval_shape` (only the structure is used).

  Returns:
    An `optax.multi_transform`: the frozen partition is `optax.set_to_zero()`, whose
    state is empty, and the trainable partition's Adam moments hold `MaskedNode`s
    (no arrays) at frozen paths.
  """
  schedule = make_schedule(opt_cfg, num_steps)
  parts = []
  if opt_cfg.clip_norm > 0:
    parts.append(optax.clip_by_global_norm(opt_cfg.clip_norm))
  parts.append(optax.adamw(schedule, b1=opt_cfg.b1, b2=opt_cfg.b2, eps=opt_cfg.eps,
                           weight_decay=opt_cfg.weight_decay))
  transforms = {TRAINABLE: optax.chain(*parts), FROZEN: optax.set_to_zero()}
  return optax.multi_transform(transforms, param_labels(params, opt_cfg.frozen))
