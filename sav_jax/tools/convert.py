"""`sav-jax convert SRC DST`: an official checkpoint -> an orbax checkpoint directory."""

from __future__ import annotations

import argparse
import logging

from sav_jax.tools import UsageError

HELP = ("convert an official .pth/.pt/.safetensors/.npz checkpoint into an orbax directory, "
        "or export an orbax directory or a training run's checkpoint to an official "
        ".safetensors/.npz/.pth file")
log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
  p.add_argument("src", help="Stereo Any Video checkpoint (or, with --vda, a VDA-only file); "
                 "an orbax directory, or a training run's WORKDIR (latest checkpoint) or "
                 "WORKDIR/checkpoints/STEP, to export")
  p.add_argument("dst", help="orbax checkpoint directory to create; when SRC is an orbax "
                 "directory, the .safetensors/.npz/.pth file to export to (for a training "
                 "checkpoint, a path without suffix makes a variables directory: params only)")
  p.add_argument("--vda", action="store_true",
                 help="SRC is a Video Depth Anything file (video_depth_anything_vits.pth): "
                      "write SAV variables with these depth-prior weights and a freshly "
                      "initialised (seeded) trainable part, to start training as the paper does")
  p.add_argument("--seed", type=int, default=0, help="init seed of the trainable part (--vda)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing DST checkpoint")


def count_params(tree) -> int:
  import jax  # pylint: disable=import-outside-toplevel
  return int(sum(x.size for x in jax.tree_util.tree_leaves(tree)))


def run(args: argparse.Namespace) -> int:
  import os  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax import convert  # pylint: disable=import-outside-toplevel

  if os.path.exists(args.dst) and not args.overwrite:
    raise UsageError(f"{args.dst} exists; pass --overwrite to replace it")
  if convert.is_orbax_checkpoint(args.src):
    variables, config = convert.restore_variables(args.src)
    if convert.is_variables_checkpoint(args.src) or os.path.splitext(args.dst)[1]:
      path = convert.export_state_dict(variables, args.dst, overwrite=args.overwrite)
      print(f"exported {args.src} -> {path} (official Stereo Any Video key names)")
    else:  # a training checkpoint -> a compact variables directory (no optimizer state)
      step = convert.find_training_checkpoint(args.src)
      convert.save_variables(args.dst, variables, {**config, "source": str(step)},
                             overwrite=args.overwrite)
      print(f"saved the params of {step} -> {args.dst}")
    return 0
  cfg = sav_jax.SAVConfig()
  kind = "vda" if args.vda else "sav"
  sd = convert.load_state_dict_of_kind(args.src, kind, {"vda": "add --vda", "sav": "drop --vda"})
  if kind == "vda":
    variables = init_with_vda(sd, cfg, args.seed)
  else:
    variables = convert.params_from_state_dict(sd, cfg)
  params = variables["params"]
  frozen = count_params(params["depthnet"]["depthanything"])
  total = count_params(params)
  convert.save_variables(args.dst, variables, {"model": cfg.to_dict(), "source": str(args.src),
                                               "kind": kind}, overwrite=args.overwrite)
  print(f"converted {args.src} ({kind}, {len(sd)} tensors) -> {args.dst}")
  print(f"  parameters: {total:,} ({total - frozen:,} trainable, {frozen:,} frozen depth prior)")
  unused = variables.get(convert.params.UNUSED_COLLECTION, {})
  if unused:
    print(f"  kept {len(unused)} tensors unused by the forward pass (for exact export)")
  return 0


def init_with_vda(vda_sd, cfg, seed: int) -> dict:
  """The whole model initialised as the official one, with the depth prior from `vda_sd`."""
  from sav_jax import convert  # pylint: disable=import-outside-toplevel
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel

  params = init_variables(cfg, seed)["params"]
  vda, unused = convert.vda_params_from_state_dict(vda_sd)
  params["depthnet"]["depthanything"] = vda
  prefix = convert.params.VDA_PREFIX
  return {"params": params, convert.params.UNUSED_COLLECTION: {prefix + k: v for k, v in unused.items()}}
