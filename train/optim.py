"""Optimizer of the official trainer: AdamW + OneCycle (linear), clipping, frozen depth prior.

Official (`train_stereoanyvideo.py: fetch_optimizer`): `AdamW(lr, weight_decay=wdecay,
eps=1e-8)` with PyTorch's default betas, `OneCycleLR(max_lr=lr, total_steps=num_steps +
100, pct_start=0.01, cycle_momentum=False, anneal_strategy="linear")` with the default
`div_factor=25` and `final_div_factor=1e4`, `clip_grad_norm_(params, 1.0)` before every
step, and every parameter whose name contains `depthanything` frozen
(`requires_grad_(False)`: no update, no optimizer state, not in the clipping norm).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import ml_collections
import optax

from sav_jax.model.init import FROZEN, TRAINABLE, param_labels, path_name  # noqa: F401


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
    raise ValueError(f"degenerate one-cycle schedule: its warm-up ends at pct_start * "
                     f"total_steps - 1 = {warm_end:g}, which must be in (0, {last:g})")

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


def check_depth_prior_frozen(labels, frozen_pattern: str) -> None:
  """Raises ValueError if `frozen_pattern` leaves a depth-prior leaf (`depthanything` in its
  path) trainable: the model stops the gradient at the prior's output (as the official
  model runs it without gradients), so such a leaf would get Adam moments and weight decay
  but never a gradient; or if it freezes every parameter (e.g. `.`, or `^`, which matches
  every path): the run would make no update in all its steps."""
  if TRAINABLE not in jax.tree.leaves(labels):
    raise ValueError(
        f"config.optimizer.frozen={frozen_pattern!r} freezes every parameter of the model: "
        "the run would train nothing; use a pattern that matches the depth prior's paths "
        "only, 'depthanything' (the default)")
  loose = [path_name(path) for path, label in jax.tree_util.tree_leaves_with_path(labels)
           if label == TRAINABLE and "depthanything" in path_name(path)]
  if loose:
    raise ValueError(
        f"config.optimizer.frozen={frozen_pattern!r} leaves {len(loose)} parameters of the "
        f"frozen depth prior trainable (e.g. {loose[0]}): the model stops its gradient, so "
        "they would only decay; use a pattern that matches 'depthanything' (the default)")


# The optimizer fields the learning-rate schedule depends on.
SCHEDULE_FIELDS = ("schedule", "schedule_steps", "lr", "pct_start", "div_factor",
                   "final_div_factor")


def _distinct(value: float, other: float) -> str:
  """`value` with the fewest significant digits (3 at least) that tell it from `other`."""
  for digits in range(3, 10):
    if f"{value:.{digits}g}" != f"{other:.{digits}g}":
      return f"{value:.{digits}g}"
  return repr(value)


def schedule_change_note(opt_cfg, num_steps: int, step: int, saved: dict,
                         updates: int | None = None) -> str | None:
  """A warning for a resume at `step` whose schedule changed: `train.num_steps` or one of
  `SCHEDULE_FIELDS` differs from the saved run's (`saved`: its `"a.b": value` fields), so
  the learning rate changes from what the saved run would have used. It gives the rate at
  `step` before and after and, where only `train.num_steps` changed a one-cycle schedule,
  the `schedule_steps` that keeps the earlier cycle. None when nothing changes, or for a
  checkpoint that saved no run config. `updates`: the updates made by `step` (steps less the
  skipped ones), which the schedule counts (default `step`)."""
  updates = step if updates is None else updates
  if not saved or "train.num_steps" not in saved:
    return None
  saved_steps = saved["train.num_steps"]
  old = ml_collections.ConfigDict(opt_cfg.to_dict())
  for field in SCHEDULE_FIELDS:
    if f"optimizer.{field}" in saved:
      old[field] = saved[f"optimizer.{field}"]
  changed = [f"train.num_steps {saved_steps} -> {num_steps}"] if saved_steps != num_steps else []
  changed += [f"optimizer.{f} {old[f]!r} -> {opt_cfg[f]!r}" for f in SCHEDULE_FIELDS
              if old[f] != opt_cfg[f]]
  if not changed:
    return None
  with jax.transfer_guard("allow"):  # host arithmetic; the training program disallows transfers
    try:
      before = float(make_schedule(old, saved_steps)(updates))
    except ValueError:  # a saved schedule this version does not build
      before = float("nan")
    after = float(make_schedule(opt_cfg, num_steps)(updates))
  if before == after:
    return None
  keep = (len(changed) == 1 and saved_steps != num_steps and old.schedule == "one_cycle"
          and old.schedule_steps <= 0)
  skipped = f" (update {updates}: {step - updates} skipped)" if updates != step else ""
  return (f"{', '.join(changed)}: the learning-rate schedule changes, the rate at step {step}"
          f"{skipped} goes from {_distinct(before, after)} to {_distinct(after, before)}"
          + (f"; to keep the earlier cycle (and then its final rate), pass "
             f"--config.optimizer.schedule_steps={saved_steps + 100}" if keep else ""))


def cycle_length(opt_cfg, num_steps: int) -> int:
  """The one-cycle schedule's `total_steps`: `optimizer.schedule_steps`, else (<= 0) the
  official `train.num_steps + 100`."""
  return opt_cfg.schedule_steps if opt_cfg.schedule_steps > 0 else num_steps + 100


def make_schedule(opt_cfg, num_steps: int) -> Callable[[Any], jax.Array]:
  """The learning-rate schedule of an optimizer config (see `configs/sceneflow.py`)."""
  if opt_cfg.schedule == "constant":
    return optax.constant_schedule(opt_cfg.lr)
  if opt_cfg.schedule != "one_cycle":
    raise ValueError(f"unknown schedule {opt_cfg.schedule!r}; expected 'one_cycle' or 'constant'")
  total = cycle_length(opt_cfg, num_steps)
  # The official loop stops the scheduler at num_steps, before the cycle ends (total is
  # num_steps + 100). A cycle set shorter than the run (`schedule_steps`) holds its final
  # lr afterwards instead of extrapolating the linear decay below zero.
  return one_cycle_linear(opt_cfg.lr, total, opt_cfg.pct_start, opt_cfg.div_factor,
                          opt_cfg.final_div_factor, stop_at=total - 1)


def schedule_summary(opt_cfg, num_steps: int) -> str:
  """The learning-rate schedule in words, for the run's log: `one-cycle (linear), from 4e-06
  up to 0.0001 at update 1200, down to 4e-10 at update 120099 of a 120100-update cycle (this
  run's last update is 119999, at 8.45e-08)`, or `constant 0.0001`."""
  if opt_cfg.schedule == "constant":
    return f"constant {opt_cfg.lr:g}"
  total = cycle_length(opt_cfg, num_steps)
  initial = opt_cfg.lr / opt_cfg.div_factor
  peak = int(round(opt_cfg.pct_start * total - 1.0))
  end = (f"down to {initial / opt_cfg.final_div_factor:.3g} at update {total - 1} of a "
         f"{total}-update cycle")
  if num_steps < total:  # its last update, num_steps - 1, comes before the cycle's last
    with jax.transfer_guard("allow"):  # one scalar, at the start
      last = float(make_schedule(opt_cfg, num_steps)(num_steps - 1))
    # updates count from 0: the run's last one is num_steps - 1 (its log line shows this rate)
    end += f" (this run's last update is {num_steps - 1}, at {last:.3g})"
  else:
    end += f", then held (this run: {num_steps} updates)"
  return f"one-cycle (linear), from {initial:.3g} up to {opt_cfg.lr:g} at update {peak}, {end}"


class TrainableVector:
  """The trainable leaves of a parameter tree as one vector, and back.

  The optimizer and the train step work on this vector: AdamW's moments are two vectors
  of the trainable size, and the update, the finite check and the norms are a handful of
  whole-vector operations instead of several per parameter leaf (the model has 142
  trainable leaves and 334 frozen ones). The tiny synthetic train step then compiles in
  less than half the time on XLA:CPU (section "Training steps: the optimizer on one
  vector" of benchmarks/README.md), and accelerators run a few large kernels in place of
  hundreds of small ones. Frozen leaves are not in it: they get no gradient, no optimizer
  state and no update.

  Args:
    labels: `param_labels` of the parameter tree.
  """

  def __init__(self, labels):
    leaves, self.treedef = jax.tree.flatten(labels)
    self.index = tuple(i for i, lab in enumerate(leaves) if lab == TRAINABLE)

  def leaves(self, tree) -> list:
    """The trainable leaves of `tree` (the parameters or a tree like them), in
    `jax.tree.leaves` order."""
    leaves = self.treedef.flatten_up_to(tree)
    return [leaves[i] for i in self.index]

  def replace(self, tree, trainable: list):
    """`tree` with its trainable leaves replaced by `trainable` (as from `leaves`)."""
    leaves = self.treedef.flatten_up_to(tree)
    for i, leaf in zip(self.index, trainable, strict=True):
      leaves[i] = leaf
    return jax.tree.unflatten(self.treedef, leaves)

  @staticmethod
  def concat(trainable: list) -> jax.Array:
    """`trainable` leaves raveled and concatenated: the vector. Shape `[size]`."""
    if not trainable:
      return jnp.zeros((0,), jnp.float32)
    return jnp.concatenate([jnp.ravel(x) for x in trainable])

  def gather(self, tree) -> jax.Array:
    """The vector of `tree`'s trainable leaves: `concat(leaves(tree))`."""
    return self.concat(self.leaves(tree))

  def scatter(self, tree, vector: jax.Array):
    """`tree` with its trainable leaves replaced by the pieces of `vector` (the inverse of
    `gather`); the frozen leaves are `tree`'s own."""
    pieces, offset = [], 0
    for leaf in self.leaves(tree):
      n = math.prod(leaf.shape)
      pieces.append(vector[offset:offset + n].reshape(leaf.shape).astype(leaf.dtype))
      offset += n
    if offset != vector.shape[0]:
      raise ValueError(f"a vector of {vector.shape[0]} values for {offset} trainable parameters")
    return self.replace(tree, pieces)

  def size(self, tree) -> int:
    """Number of trainable values in `tree` (arrays or shapes)."""
    leaves = self.treedef.flatten_up_to(tree)
    return sum(math.prod(leaves[i].shape) for i in self.index)


def clip_grad_norm_like_torch(max_norm: float) -> optax.GradientTransformation:
  """`torch.nn.utils.clip_grad_norm_(params, max_norm)` as an optax transformation: the
  gradients times `min(1, max_norm / (norm + 1e-6))` (optax's `clip_by_global_norm` divides
  by the norm alone). Its state is empty, as `clip_by_global_norm`'s: checkpoints of either
  restore with the other."""

  def update(updates, state, params=None):
    del params
    norm = jnp.sqrt(sum(jnp.sum(jnp.square(g)) for g in jax.tree.leaves(updates)))
    scale = jnp.minimum(1.0, max_norm / (norm + 1e-6))
    return jax.tree.map(lambda g: (g * scale).astype(g.dtype), updates), state

  return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def make_optimizer(opt_cfg, num_steps: int) -> optax.GradientTransformation:
  """Clip + AdamW, on the `TrainableVector` of the parameters.

  Args:
    opt_cfg: the `optimizer` block of a config.
    num_steps: training length (sets the one-cycle length as the official script).

  Returns:
    An optax transformation to `init` and `update` with vectors (`TrainableVector.gather`
    of the parameters and of their gradients). Its state: the clipping's (empty) and
    AdamW's step count and two moment vectors.
  """
  schedule = make_schedule(opt_cfg, num_steps)
  parts = []
  if opt_cfg.clip_norm > 0:
    parts.append(clip_grad_norm_like_torch(opt_cfg.clip_norm))
  parts.append(optax.adamw(schedule, b1=opt_cfg.b1, b2=opt_cfg.b2, eps=opt_cfg.eps,
                           weight_decay=opt_cfg.weight_decay))
  return optax.chain(*parts)
