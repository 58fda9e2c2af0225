"""`sav-jax convert SRC DST`: an official checkpoint -> an orbax checkpoint directory.

Also the other way (an orbax directory or a training run's checkpoint -> an official
state-dict file) and file to file (e.g. `.pth` -> `.safetensors`, checked on the way).
"""

from __future__ import annotations

import argparse
import logging

from sav_jax._checks import check_utf8_path
from sav_jax.tools import UsageError, check_output_dir, user_path

HELP = ("convert an official .pth/.pt/.safetensors/.npz checkpoint into an orbax directory "
        "(or another state-dict file), or export an orbax directory or a training run's "
        "checkpoint to an official .safetensors/.npz/.pth file")
log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
  p.add_argument("src", type=user_path, help="Stereo Any Video checkpoint (or, with --vda, a VDA-only file); "
                 "an orbax directory, or a training run's WORKDIR (latest checkpoint) or "
                 "WORKDIR/checkpoints/STEP, to export")
  p.add_argument("dst", type=user_path, help="orbax checkpoint directory to create, or a .safetensors/.npz/"
                 ".pth/.pt/.bin file (the last three need torch) to write the (checked) "
                 "weights to under the official key names; for a "
                 "training checkpoint SRC, a path without suffix makes a variables directory "
                 "(params only)")
  p.add_argument("--vda", action="store_true",
                 help="SRC is a Video Depth Anything file (video_depth_anything_vits.pth): "
                      "write SAV variables with these depth-prior weights and a freshly "
                      "initialised (seeded) trainable part, to start training as the paper does")
  p.add_argument("--seed", type=int, default=0,
                 help="init seed of the trainable part (--vda; default 0)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing DST checkpoint")


def count_params(tree) -> int:
  import jax  # pylint: disable=import-outside-toplevel
  return int(sum(x.size for x in jax.tree_util.tree_leaves(tree)))


# File formats a DST may be mistaken for (`.npy` for `.npz`): refused, not made orbax folders.
OTHER_FILE_SUFFIXES = (".npy", ".h5", ".hdf5", ".pkl", ".pickle", ".json", ".msgpack", ".onnx",
                       ".zip", ".gz", ".mat")


def check_destination(src: str, dst: str, to_file: bool, overwrite: bool) -> None:
  """Raises UsageError before anything is read if DST cannot or must not be written."""
  import os  # pylint: disable=import-outside-toplevel

  from sav_jax import convert  # pylint: disable=import-outside-toplevel
  if os.path.realpath(src) == os.path.realpath(dst):
    raise UsageError(f"SRC and DST are the same path ({dst}); write to another one")
  check_output_dir(os.path.dirname(os.path.abspath(dst)), flag=f"DST {dst}: folder")
  if not to_file:  # (orbax's TensorStore failed on other bytes, after the conversion's work)
    check_utf8_path(os.path.abspath(dst), "orbax checkpoint folder DST")
  if not os.path.lexists(dst):
    return
  if os.path.islink(dst) and not os.path.exists(dst):  # (was "exists", then "not a file")
    raise UsageError(f"{dst} is a symbolic link to a missing path ({os.readlink(dst)}); it "
                     "is not written through, even with --overwrite: remove the link or give "
                     "another DST")
  if not to_file and os.path.isdir(dst) and not os.path.islink(dst) and not os.listdir(dst):
    return  # an empty folder made for it: nothing to replace
  if not overwrite:
    raise UsageError(f"{dst} exists; pass --overwrite to replace it")
  if to_file and not os.path.isfile(dst):
    raise UsageError(f"{dst} exists and is not a file; it is not replaced, even with "
                     "--overwrite")
  if not to_file and not convert.is_variables_checkpoint(dst):
    raise UsageError(f"{dst} exists and is not a `sav-jax convert` variables folder; it is not "
                     "replaced, even with --overwrite")


def run(args: argparse.Namespace) -> int:
  import os  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax import convert  # pylint: disable=import-outside-toplevel

  suffix = os.path.splitext(args.dst)[1].lower()
  to_file = suffix in convert.torch_io.WRITE_SUFFIXES
  if not to_file and suffix in (*convert.torch_io.TORCH_SUFFIXES, *OTHER_FILE_SUFFIXES):
    raise UsageError(f"{args.dst}: cannot write a {suffix} file; name a "
                     f"{'/'.join(convert.torch_io.WRITE_SUFFIXES)} file, or a folder name "
                     "without a checkpoint suffix for an orbax directory")
  if args.seed < 0:
    raise UsageError(f"--seed must be >= 0, got {args.seed}")
  check_destination(args.src, args.dst, to_file, args.overwrite)
  if to_file:  # e.g. a .pth without torch: before the conversion's work
    convert.torch_io.check_writer(args.dst)
  if os.path.isdir(args.src):  # restore_variables says what a folder must hold
    if args.vda:
      raise UsageError(f"--vda takes a Video Depth Anything file, not a folder ({args.src})")
    if convert.is_variables_checkpoint(args.src) and not to_file:
      raise UsageError(f"{args.src} is already an orbax variables checkpoint: name a "
                       f"{'/'.join(convert.torch_io.WRITE_SUFFIXES)} DST to export it (or copy "
                       "the folder)")
    variables, config = convert.restore_variables(args.src)
    for notes in (convert.random_prior_note, convert.untrained_note):
      note = notes(config, args.src)
      if note and to_file:  # an orbax output keeps the note in its config; a file has none
        log.warning("%s (%s will not record it)", note, args.dst)
    if convert.is_variables_checkpoint(args.src) or to_file:
      from sav_jax.tools.infer import config_from_dict  # pylint: disable=import-outside-toplevel
      try:  # the checks name the parameters; say which checkpoint they are of
        sd = convert.state_dict_from_params(variables, config_from_dict(config, args.src))
      except convert.CheckpointError as e:
        raise convert.CheckpointError(f"{args.src}: {e}") from e
      path = convert.save_state_dict(sd, args.dst, overwrite=args.overwrite)
      print(f"exported {args.src} -> {path} (official Stereo Any Video key names)")
    else:  # a training checkpoint -> a compact variables directory (no optimizer state)
      step = convert.find_training_checkpoint(args.src)
      convert.save_variables(args.dst, variables, {**config, "source": str(step)},
                             overwrite=args.overwrite)
      print(f"saved the params of {step} -> {args.dst}")
    return 0
  kind = "vda" if args.vda else "sav"
  sd = convert.load_state_dict_of_kind(args.src, kind, {"vda": "add --vda", "sav": "drop --vda"})
  # The depth prior's size as the file has it (the paper's model: ViT-S).
  encoder = convert.params.vda_encoder_of(sd, "" if kind == "vda" else convert.params.VDA_PREFIX)
  cfg = sav_jax.SAVConfig(vda_encoder=encoder or "vits")
  try:
    if kind == "vda":
      variables = init_with_vda(sd, cfg, args.seed)
    else:
      variables = convert.params_from_state_dict(sd, cfg)
  except ValueError as e:  # the report names the keys; say which file they are of
    raise convert.CheckpointError(f"{args.src}: {e}") from e
  if to_file:  # checked by the conversion, written back with the official names
    path = convert.export_state_dict(variables, args.dst, overwrite=args.overwrite, cfg=cfg)
    if kind == "vda":  # an orbax output records it (`untrained_note`); a file cannot
      log.warning("%s holds a freshly initialised stereo network (seed %d) beside the depth "
                  "prior of %s: an initialisation for training, not a model to run, and "
                  "nothing in the file says so", path, args.seed, args.src)
    print(f"converted {args.src} ({kind}, {len(sd)} tensors) -> {path} (official Stereo Any "
          "Video key names)")
    return 0
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
  from sav_jax.model import init  # pylint: disable=import-outside-toplevel
  from sav_jax.model.vda import VideoDepthAnything  # pylint: disable=import-outside-toplevel

  params = init.init_variables(cfg, seed)["params"]
  vda, unused = convert.vda_params_from_state_dict(
      vda_sd, VideoDepthAnything(**cfg.vda),
      init.abstract_variables(cfg)["params"]["depthnet"]["depthanything"])
  params["depthnet"]["depthanything"] = vda
  prefix = convert.params.VDA_PREFIX
  return {"params": params, convert.params.UNUSED_COLLECTION: {prefix + k: v for k, v in unused.items()}}
