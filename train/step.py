"""The jitted train step (one for 1 or N devices) and the evaluation forward pass."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec as P
import optax

from sav_jax import runtime
from train import loss as loss_lib
from train import optim
from train.state import DATA_AXIS, TrainState, data_devices, data_sharding, replicated


def per_device_apply(model, mesh=None):
  """`model.apply(variables, left, right, **kwargs)`, run by each device on its own clips.

  Under a mesh whose `data` axis has several devices, the forward pass is a `shard_map`
  over that axis: every device runs the model on its share of the batch (the variables
  replicated), as one device runs the whole batch. Traced on the global batch instead,
  the model's whole-batch steps moved clips between devices in every step: the views
  concatenated along the batch axis and split again (all-to-alls and collective permutes
  of the frames and 1/4 feature maps), and the frame blocks of `cfg.frame_block_mb`
  (`layers.in_frame_blocks`, sized for the global batch: `sceneflow.py`'s 80 frames in
  blocks of 4 on 8 devices) gathered the frames, so that each device ran the encoders on
  every clip of the batch. The output's disparities `[P, B, ...]` stay split on B. Each
  device's `rngs` are folded with its index on `data`: with the one key of the step, every
  device drew the same random numbers (a dropout mask, say) for its own clips.
  Without a mesh, or with one device on `data`, plain `model.apply`.
  """
  if mesh is None or data_devices(mesh) == 1:
    return model.apply
  batch = P(DATA_AXIS)

  def apply(variables, left, right, *, rngs=None, **kwargs):
    def local(variables, left, right, rngs):
      if rngs is not None:
        index = jax.lax.axis_index(DATA_AXIS)
        rngs = jax.tree.map(lambda key: jax.random.fold_in(key, index), rngs)
      return model.apply(variables, left, right, **kwargs,
                         **({} if rngs is None else {"rngs": rngs}))

    return _shard_map(local, mesh=mesh, in_specs=(P(), batch, batch, P()),
                      out_specs=P(None, DATA_AXIS))(variables, left, right, rngs)

  return apply


def _shard_map(fn, **kwargs):
  """`jax.shard_map` without its replication checks (jax >= 0.7), or the experimental one
  that jax 0.6, which pyproject.toml allows, has instead."""
  if hasattr(jax, "shard_map"):
    return jax.shard_map(fn, check_vma=False, **kwargs)
  from jax.experimental.shard_map import shard_map  # pylint: disable=g-import-not-at-top
  return shard_map(fn, check_rep=False, **kwargs)


def make_train_step(model, tx: optax.GradientTransformation, config, labels, mesh=None):
  """`train_step(state, batch) -> (state, metrics)` (not jitted; see `jit_train_step`).

  The batch is `left/right [B, T, H, W, 3]` (uint8 or float, 0..255), `disparity
  [B, T, H, W]` (positive) and `valid [B, T, H, W]`. A non-finite loss, gradient norm or
  update norm leaves params and optimizer state untouched and increments
  `num_skipped`; `step` always advances (it counts consumed batches), while the
  learning-rate schedule follows the number of applied updates.

  The gradient, the optimizer and the update work on the `optim.TrainableVector` of the
  params: the frozen leaves (the depth prior) are constants of the loss, so autodiff
  builds no backward pass for them, and they come out of the step untouched.

  Args:
    model: `sav_jax.StereoAnyVideo`.
    tx: optimizer from `train.optim.make_optimizer`.
    config: full training config (`train.iters`, `loss.*`, `optimizer.*`).
    labels: optimizer labels of the params (`train.optim.param_labels`).
    mesh: the mesh the step runs on (`jit_train_step`'s): the forward pass then runs on
      each device's own clips (`per_device_apply`); None traces it on the global batch.
  """
  apply = per_device_apply(model, mesh)
  schedule = optim.make_schedule(config.optimizer, config.train.num_steps)
  iters = config.train.iters
  vector = optim.TrainableVector(labels)
  microbatches = check_microbatches(config)

  def loss_and_grads(state, trainable, batch, rng):
    """`((loss, metrics), grads of the trainable leaves)` of one (micro-)batch."""
    left = batch["left"].astype(jnp.float32)
    right = batch["right"].astype(jnp.float32)

    def loss_fn(trainable):
      out = apply({"params": vector.replace(state.params, trainable)}, left, right,
                  iters=iters, rngs={"dropout": rng})
      return loss_lib.sequence_loss(out.disparities, batch["disparity"], batch["valid"],
                                    gamma=config.loss.gamma,
                                    max_disparity=config.loss.max_disparity,
                                    per_sample=config.loss.per_sample)

    return jax.value_and_grad(loss_fn, has_aux=True)(trainable)

  def accumulated(state, trainable, batch, rng):
    """`loss_and_grads` of the batch as the mean over `microbatches` equal parts, run one
    after the other (`lax.scan`): the activations of one part at a time. Per-clip losses
    and metrics make the mean of the parts' means the batch's mean; the accuracy metrics,
    means over a part's measured frames, are weighted by their count (a part without any,
    sparse ground truth outside its crops, would pull them toward 0). Part j takes clips j,
    j + k, j + 2k... (k = microbatches), so that every device holds its share of it."""
    parts = jax.tree.map(lambda x: jnp.swapaxes(
        x.reshape(x.shape[0] // microbatches, microbatches, *x.shape[1:]), 0, 1), batch)

    def body(total, part):
      j, clips = part
      (loss, metrics), grads = loss_and_grads(state, trainable, clips, jax.random.fold_in(rng, j))
      metrics = {k: v * metrics["measured_frames"] if k in loss_lib.MEASURED_METRICS else v
                 for k, v in metrics.items()}
      return jax.tree.map(jnp.add, total, ((loss, metrics), grads)), None

    # The sums start at zero: the loss's scalars (its shapes from the loss alone: tracing
    # the model for them cost as much as the step's own trace) and the gradient's leaves.
    first = jax.tree.map(lambda x: x[0], parts)
    scalars = jax.eval_shape(lambda d, v: loss_lib.sequence_loss(
        d[None], d, v, per_sample=config.loss.per_sample), first["disparity"], first["valid"])
    zeros = (jax.tree.map(lambda s: jnp.zeros(s.shape, jnp.float32), scalars),
             jax.tree.map(jnp.zeros_like, trainable))
    total, _ = jax.lax.scan(body, zeros, (jnp.arange(microbatches), parts))
    (loss, metrics), grads = jax.tree.map(lambda x: x / microbatches, total)
    measured = metrics["measured_frames"]  # (0 in a batch without any: the sums are 0 too)
    metrics = {k: v / jnp.maximum(measured, 1e-12) if k in loss_lib.MEASURED_METRICS else v
               for k, v in metrics.items()}
    return (loss, metrics), grads

  def train_step(state: TrainState, batch):
    step_rng = jax.random.fold_in(jax.random.wrap_key_data(state.rng), state.step)
    trainable = vector.leaves(state.params)
    # The gradient of the leaves, then one concatenation: differentiating through slices
    # of the vector would sum one vector-sized padded gradient per leaf.
    if microbatches == 1:
      (loss, metrics), grads = loss_and_grads(state, trainable, batch, step_rng)
    else:
      (loss, metrics), grads = accumulated(state, trainable, batch, step_rng)
    grads, theta = vector.concat(grads), vector.concat(trainable)
    updates, new_opt_state = tx.update(grads, state.opt_state, theta)
    l2_grads = jnp.linalg.norm(grads)
    l2_updates = jnp.linalg.norm(updates)
    finite = jnp.isfinite(loss) & jnp.isfinite(l2_grads) & jnp.isfinite(l2_updates)
    new_theta = jnp.where(finite, optax.apply_updates(theta, updates), theta)
    num_updates = state.step - state.num_skipped
    new_state = state.replace(
        step=state.step + 1,
        params=vector.scatter(state.params, new_theta),
        opt_state=jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_opt_state,
                               state.opt_state),
        num_skipped=state.num_skipped + jnp.where(finite, 0, 1).astype(jnp.int32))
    metrics = dict(metrics, loss=loss, l2_grads=l2_grads, l2_updates=l2_updates,
                   l2_params=jnp.linalg.norm(new_theta),
                   lr=schedule(num_updates), finite=finite.astype(jnp.float32),
                   num_skipped=new_state.num_skipped)
    return new_state, metrics

  return train_step


def check_microbatches(config) -> int:
  """`config.train.microbatches` (1 where a config has no such field), checked.

  Raises:
    ValueError: naming the field, unless it is an integer >= 1 that divides the batch, and
      the loss is per clip (`loss.per_sample`) when it is more than 1.
  """
  k = config.train.get("microbatches", 1)
  batch = config.train.batch_size
  if isinstance(k, bool) or not isinstance(k, int) or k < 1:
    raise ValueError(f"config.train.microbatches={k!r}: expected an integer >= 1")
  if batch % k:
    raise ValueError(f"config.train.microbatches={k} does not divide "
                     f"config.train.batch_size={batch}")
  if k > 1 and not config.loss.per_sample:
    raise ValueError(f"config.train.microbatches={k} needs config.loss.per_sample=True (a loss "
                     "pooled over the batch's pixels is not the mean of the parts' losses)")
  return k


def jit_train_step(train_step, state_shardings, mesh):
  """jit with the state replicated, the batch on `data`, and the old state donated."""
  batch_sharding = data_sharding(mesh)
  return jax.jit(train_step, in_shardings=(state_shardings, batch_sharding),
                 out_shardings=(state_shardings, replicated(mesh)), donate_argnums=(0,))


def make_eval_fn(model, iters: int, params_sharding, mesh):
  """Jitted `predict(params, left, right) -> [B, T, H, W]` final disparity (batch on `data`).

  The absolute value, as the official evaluator (`forward_batch_test`) and `python -m eval`
  score it: a pixel predicted with the wrong sign is not a large error there.
  """
  dsh = data_sharding(mesh)
  apply = per_device_apply(model, mesh)

  @functools.partial(jax.jit, in_shardings=(params_sharding, dsh, dsh), out_shardings=dsh,
                     compiler_options=runtime.inference_compiler_options())
  def predict(params, left, right):
    out = apply({"params": params}, left.astype(jnp.float32), right.astype(jnp.float32),
                iters=iters, final_only=True)
    return jnp.abs(out.disparities[0])

  return predict
