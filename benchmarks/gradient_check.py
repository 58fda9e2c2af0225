"""Gradients against the official PyTorch model: w.r.t. the frames and every parameter.

    python benchmarks/gradient_check.py --repo CHECKOUT --torch-interpreter TORCH_ENV/bin/python

The parity tests compare forward values with the official outputs (`../shared/fixtures`);
this script compares the backward pass. Both models get the fixtures' deterministic weights
(`make_weights.py`, seed 0, from `--fixtures`, default `../shared/fixtures` or
`SAV_FIXTURES`) and the same frames (`--frames` x `--height` x `--width`, uniform 0..255,
the right view the left shifted by 3 px), and differentiate
`loss = mean |disparity_final - 3|` (the test-mode output, `iters=--iters`) with respect to
the left and right frames and to every parameter; with `--training-loss`, the training loss
instead: every prediction of the three scales (`test_mode=False` there) against a
ground truth of `3 + 2 sin(x / 5)` px (invalid in one corner), weighted as the official
sequence loss (`train/loss.py`'s `sequence_loss` here; the same formula written in torch for
the official side, whose repository does not ship its loss file). The official side runs in a separate
Python with torch (`--torch-interpreter`; `pip install torch==2.13.0 easydict einops opt_einsum
unfoldNd scipy opencv-python-headless tqdm`), importing the official code from `--repo` as
`benchmarks/official_torch.py` does (nothing of it is copied here); sav-jax runs here, in
float32 at "highest" precision. The frozen depth prior's parameters get no gradient on either
side (`requires_grad=False` there, `stop_gradient` here); gradients w.r.t. the frames flow
through it on both.

Prints, for the two frame gradients and for the parameters (the worst of them, and how many
exceed 1e-3 relative), the largest absolute difference relative to the largest magnitude of
the official gradient.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--repo", required=True, help="a checkout of the official stereoanyvideo")
  p.add_argument("--torch-interpreter", help="a Python with torch, for the official side")
  p.add_argument("--fixtures", default=os.environ.get("SAV_FIXTURES",
                                                      str(HERE.parents[1] / "shared/fixtures")))
  p.add_argument("--frames", type=int, default=2)
  p.add_argument("--height", type=int, default=32)
  p.add_argument("--width", type=int, default=64)
  p.add_argument("--iters", type=int, default=2)
  p.add_argument("--training-loss", action="store_true",
                 help="differentiate the training loss over all predictions instead")
  p.add_argument("--torch-out", help=argparse.SUPPRESS)  # the official side's own run
  return p.parse_args(argv)


def frames(a) -> tuple[np.ndarray, np.ndarray]:
  """`[1, T, H, W, 3]` float32 left and right frames."""
  rng = np.random.default_rng(0)
  left = rng.uniform(0, 255, (1, a.frames, a.height, a.width, 3)).astype(np.float32)
  return left, np.roll(left, -3, axis=3)


def ground_truth(a) -> tuple[np.ndarray, np.ndarray]:
  """`[1, T, H, W]` disparity and validity for `--training-loss`."""
  x = np.arange(a.width, dtype=np.float32)
  disparity = np.broadcast_to(3 + 2 * np.sin(x / 5), (1, a.frames, a.height, a.width))
  valid = np.ones(disparity.shape, bool)
  valid[..., :a.height // 4, :a.width // 4] = False
  return np.ascontiguousarray(disparity, np.float32), valid


def weights(a) -> dict:
  sys.path.insert(0, a.fixtures)
  import make_weights  # pylint: disable=import-outside-toplevel
  return make_weights.make_state_dict(str(pathlib.Path(a.fixtures) / "sav_manifest.json"), 0)


def torch_side(a) -> None:
  import torch  # pylint: disable=import-outside-toplevel
  sys.path.insert(0, str(HERE))
  from official_torch import build_official_model  # pylint: disable=import-outside-toplevel
  model = build_official_model(pathlib.Path(a.repo).resolve())
  model.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in weights(a).items()})
  for name, param in model.named_parameters():  # as the official training script
    param.requires_grad_("depthanything" not in name)
  if a.training_loss:  # the training script's modes: train(), then freeze_bn() (the model has
    model.train()      # no BatchNorm and its dropouts have p=0: the same values as eval())
    if hasattr(model, "freeze_bn"):
      model.freeze_bn()
  left, right = (torch.from_numpy(np.ascontiguousarray(x.transpose(0, 1, 4, 2, 3))
                                  ).requires_grad_(True) for x in frames(a))
  if a.training_loss:  # [N, T, B, 1, H, W]: positive = disparity (the training target)
    preds = torch.stack(list(model(left, right, iters=a.iters, test_mode=False)))[:, :, :, 0]
    gt, valid = (torch.from_numpy(z.transpose(1, 0, 2, 3)) for z in ground_truth(a))
    n = preds.shape[0]
    gamma = 0.9 ** (15 / (n - 1)) if n > 1 else 1.0
    loss = 0
    for i in range(n):  # per frame: the mean over its valid pixels, then over the frames
      err = (preds[i] - gt).abs()
      per_frame = torch.stack([err[t][valid[t]].mean() for t in range(gt.shape[0])])
      loss = loss + gamma ** (n - 1 - i) * per_frame.mean()
  else:
    out = model(left, right, iters=a.iters, test_mode=True)
    loss = (out - 3).abs().mean()
  loss.backward()
  grads = {f"param/{n}": p.grad.numpy() for n, p in model.named_parameters()
           if p.grad is not None}
  np.savez(a.torch_out, loss=loss.item(),
           left=left.grad.numpy().transpose(0, 1, 3, 4, 2),
           right=right.grad.numpy().transpose(0, 1, 3, 4, 2), **grads)


def jax_side(a) -> dict:
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.convert.params import state_dict_from_params  # pylint: disable=import-outside-toplevel
  jax.config.update("jax_default_matmul_precision", "highest")
  cfg = sav_jax.SAVConfig()
  variables = sav_jax.convert.params_from_state_dict(weights(a), cfg)
  model = sav_jax.StereoAnyVideo(cfg)

  def loss(v, left, right):
    if a.training_loss:
      sys.path.insert(0, str(HERE.parent))  # the repository: `train` is not installed
      from train.loss import sequence_loss  # pylint: disable=import-outside-toplevel
      out = model.apply(v, left, right, iters=a.iters).disparities
      return sequence_loss(out, *(jnp.asarray(z) for z in ground_truth(a)))[0]
    out = model.apply(v, left, right, iters=a.iters, final_only=True).disparities
    return jnp.abs(out - 3).mean()

  left, right = frames(a)
  value, (g_vars, g_left, g_right) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))(
      variables, left, right)
  sd = state_dict_from_params(jax.device_get(g_vars), cfg)
  return {"loss": float(value), "left": np.asarray(g_left), "right": np.asarray(g_right),
          **{f"param/{k}": v for k, v in sd.items()}}


def relative_l2(ours: np.ndarray, ref: np.ndarray) -> float:
  """||ours - ref|| / ||ref|| (||ours|| when ref is 0)."""
  scale = float(np.linalg.norm(ref))
  return float(np.linalg.norm(ours - ref)) / scale if scale > 0 else float(np.linalg.norm(ours))


def official_outputs(a, argv, script: str) -> dict:
  """The arrays the official side writes: `script` run again with the same arguments in
  `--torch-interpreter`, with `--torch-out` (a temporary file)."""
  if not a.torch_interpreter:
    raise SystemExit("--torch-interpreter is required (a Python with torch for the official side)")
  sys.path.insert(0, str(HERE))
  from official_torch import repo_problem  # pylint: disable=import-outside-toplevel
  problem = repo_problem(a.repo)
  if problem:
    raise SystemExit(problem)
  if not (pathlib.Path(a.fixtures) / "make_weights.py").is_file():
    raise SystemExit(f"--fixtures {a.fixtures}: no make_weights.py there; give the oracle "
                     "fixtures folder (or set SAV_FIXTURES)")
  if shutil.which(a.torch_interpreter) is None:
    raise SystemExit(f"--torch-interpreter {a.torch_interpreter}: no such program")
  has_torch = "import importlib.util, sys; sys.exit(importlib.util.find_spec('torch') is None)"
  if subprocess.run([a.torch_interpreter, "-c", has_torch], check=False).returncode:
    raise SystemExit(f"--torch-interpreter {a.torch_interpreter}: torch is not installed there")
  with tempfile.TemporaryDirectory() as tmp:
    out = pathlib.Path(tmp) / "official.npz"
    try:
      subprocess.run([a.torch_interpreter, script, *(argv if argv is not None else sys.argv[1:]),
                      "--torch-out", str(out)], check=True)
    except subprocess.CalledProcessError as e:
      raise SystemExit(f"the official side ({a.torch_interpreter}) failed with exit status "
                       f"{e.returncode}: its error is above") from None
    return dict(np.load(out))


def main(argv=None) -> int:
  a = parse_args(argv)
  if a.torch_out:
    torch_side(a)
    return 0
  ref = official_outputs(a, argv, __file__)
  ours = jax_side(a)
  print(f"loss: official {float(ref['loss']):.7f}, sav-jax {ours['loss']:.7f}")
  for name in ("left", "right"):
    print(f"d loss / d {name} frames: relative L2 difference "
          f"{relative_l2(ours[name], ref[name]):.2e}")
  params = sorted(k for k in ref if k.startswith("param/"))
  missing = [k for k in params if k not in ours]
  top = max(float(np.abs(ref[k]).max()) for k in params)
  # Biases in front of an instance norm have a gradient of exactly 0 (the norm removes them):
  # both sides give float32 noise there; it is reported, not compared.
  zero = [k for k in params if k not in missing and float(np.abs(ref[k]).max()) < 1e-6 * top]
  errors = {k: relative_l2(ours[k], ref[k]) for k in params if k not in missing + zero}
  groups: dict[str, list[float]] = {}
  for k, e in errors.items():
    groups.setdefault(k[6:].split(".")[0], []).append(e)
  noise = max((float(np.abs(ours[k]).max()) for k in zero), default=0.0)
  print(f"parameters with a gradient (the official trainable ones): {len(params)}; "
        f"{len(missing)} missing here; {len(zero)} structurally 0 (official max < 1e-6 of the "
        f"largest gradient, {top:.1e}; ours at most {noise:.1e} there)")
  for g, es in sorted(groups.items()):
    print(f"  {g}: {len(es)} tensors, relative L2 difference median {np.median(es):.1e}, "
          f"max {max(es):.1e}")
  frozen = [k for k in ours if k.startswith("param/") and "depthanything" in k
            and not k.endswith("pos_encoder.pe") and np.abs(ours[k]).max() > 0]
  print(f"depth prior parameters with a gradient here: {len(frozen)} (official: none, "
        "requires_grad=False)")
  return 0


if __name__ == "__main__":
  sys.exit(main())
