"""Config -> grain training stream and held-out validation clips.

`config.data.sources` names the training sources, each with a `dataset` ("synthetic" or
a `sav_jax.data.registry` name such as "flyingthings3d", "dynamic_replica") and a `weight`;
`config.data.mixing` says how weights combine ("concat": official concatenation, so a
dataset's share is weight x number of clips; "ratio": weights are the shares).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging

import jax

from sav_jax._checks import plural
from sav_jax.data import pipeline
from sav_jax.data.synthetic import SyntheticConfig, config_from_block

log = logging.getLogger(__name__)


def synthetic_config(data_cfg, gen_cfg, seed: int) -> SyntheticConfig:
  """`SyntheticConfig` at the data block's clip shape, with generator overrides."""
  return config_from_block(
      gen_cfg, "config.data.synthetic", own=("num_clips",),
      set_by={"frames": "config.data.frames", "height": "config.data.crop",
              "width": "config.data.crop"},
      frames=data_cfg.frames, height=data_cfg.crop[0], width=data_cfg.crop[1], seed=seed)


@contextlib.contextmanager
def _naming(where: str):
  """Prefixes `where` (the config fields behind the data) to a ValueError,
  FileNotFoundError or NotADirectoryError that does not name a config field itself."""
  try:
    yield
  except (ValueError, FileNotFoundError, NotADirectoryError) as e:
    if str(e).startswith("config."):
      raise
    cls = ValueError if isinstance(e, ValueError) else type(e)
    raise cls(f"{where}: {e}") from e


def _source(config, spec, split: str, seed: int):
  """`(MapDataset, random map or None, digest of its clips)` of one source."""
  data = config.data
  if spec.dataset == "synthetic":
    cfg = synthetic_config(data, data.synthetic, seed)
    digest = hashlib.sha256(f"{cfg!r} {data.synthetic.num_clips}".encode()).hexdigest()[:16]
    return pipeline.synthetic_source(cfg, data.synthetic.num_clips), None, digest
  items = pipeline.registry_clips(spec.dataset, source_root(config, spec), data.frames,
                                  split=split, seed=config.seed)
  missing = pipeline.without_ground_truth(items)
  if missing:  # found here, not at the step whose batch first draws one of their clips
    raise ValueError(
        f"{plural(len(missing), 'sequence')} of {spec.dataset}/{split} without ground truth "
        f"(for the folder dataset: no disparity/ folder): {pipeline.sequences_named(missing)}; "
        "every training clip needs it: move such sequences out of the training split "
        "(python -m eval and sav-jax infer run on them)")
  return (pipeline.clips_source(items, data.skip_unreadable),
          pipeline.Augment(tuple(data.crop), augment_overrides(config)),
          pipeline.clips_digest(items))


def source_root(config, spec) -> str:
  """A training source's data root: its own `root`, else `config.data.root`."""
  return spec.get("root") or config.data.root


def augment_overrides(config) -> tuple[tuple[str, object], ...]:
  """`config.data.augment` as `pipeline.Augment.overrides`."""
  return tuple(sorted(dict(config.data.augment).items()))


def train_dataset(config, process_index=None, process_count=None, clips: dict | None = None):
  """The per-process batched training `grain.IterDataset` of a config.

  `clips`: a dict to fill with each source's `{"dataset", "clips", "digest"}` (how many clips,
  and which: `pipeline.clips_digest`), saved with the checkpoints so that a resumed run can
  tell whether its data changed (`changed_clips`)."""
  count = jax.process_count() if process_count is None else process_count
  batch = config.train.batch_size
  if batch % count:
    raise ValueError(f"config.train.batch_size={batch} is not divisible by {count} processes")
  sources, transforms, weights = [], [], []
  for name, spec in sorted(config.data.sources.items()):
    where = (f"config.data.sources.{name}.dataset={spec.dataset!r} (config.data.synthetic)"
             if spec.dataset == "synthetic" else
             f"config.data.sources.{name}.dataset={spec.dataset!r}, "
             + (f"config.data.sources.{name}.root={spec.root!r}" if spec.get("root") else
                f"config.data.root={config.data.root!r}"))
    with _naming(where):
      src, tf, digest = _source(config, spec, "train", seed=config.data.synthetic.seed)
    if clips is not None:
      clips[name] = {"dataset": spec.dataset, "clips": len(src), "digest": digest,
                     "seeding": pipeline.SEEDING}
    log.info("training source %s: %s, %d clips, weight %g", name, spec.dataset, len(src),
             spec.weight)
    sources.append(src)
    transforms.append(tf)
    weights.append(spec.weight)
  return pipeline.make_train_dataset(
      sources, weights, batch_size=batch // count, seed=config.seed, mode=config.data.mixing,
      transforms=transforms, process_index=process_index, process_count=process_count,
      num_threads=config.data.num_threads, prefetch=config.data.prefetch,
      worker_count=config.data.worker_count)


def changed_clips(saved: dict, now: dict) -> list[str]:
  """The sources whose clips differ between `train_dataset(clips=...)` records (a resumed
  run's and its checkpoint's), as `name: what changed`; [] where nothing did or the
  checkpoint has no record."""
  if not isinstance(saved, dict) or not saved:
    return []
  out = []
  for name in sorted(set(saved) | set(now)):
    old, new = saved.get(name), now.get(name)
    if old == new:
      continue
    if old is None or new is None:
      out.append(f"{name}: {'added' if old is None else 'removed'}")
    elif old.get("clips") != new.get("clips"):
      out.append(f"{name}: {old.get('clips')} -> {new.get('clips')} clips")
    elif old.get("digest") != new.get("digest"):
      out.append(f"{name}: other clips ({new.get('clips')})")
    else:  # a checkpoint of sav-jax before the hashed seeds: another shuffle of the same clips
      out.append(f"{name}: the clip order and augmentation are drawn with other seeds "
                 "(the checkpoint is of sav-jax before 2026-12-05)")
  return out


def eval_clips(config) -> list[dict]:
  """The fixed held-out clips (identical on every process), at the training crop."""
  ev = config.eval
  if ev.dataset == "synthetic":
    # A seed the training stream never uses: clips are disjoint from training.
    with _naming(f"config.eval.dataset='synthetic' (config.eval.synthetic_seed="
                 f"{ev.synthetic_seed!r}, config.data.synthetic)"):
      cfg = synthetic_config(config.data, config.data.synthetic, seed=ev.synthetic_seed)
      ds = pipeline.synthetic_source(cfg, ev.num_clips)
    return pipeline.fixed_clips(ds, ev.num_clips)
  # Consecutive frames, as the evaluation's (TEPE measures the change between frames).
  root, field = (ev.root, "eval.root") if ev.get("root") else (config.data.root, "data.root")
  with _naming(f"config.eval.dataset={ev.dataset!r}, config.eval.split={ev.split!r}, "
               f"config.{field}={root!r}, config.data.crop={tuple(config.data.crop)!r}"):
    src = pipeline.registry_source(ev.dataset, root, config.data.frames, split=ev.split,
                                   consecutive=True)
    stride = max(1, len(src) // ev.num_clips)  # spread over the split, deterministically
    picked = src[::stride][:ev.num_clips]
    crop = tuple(config.data.crop)
    # (reading and cropping the clips here: a size or ground-truth problem names the fields)
    return pipeline.fixed_clips(picked, min(ev.num_clips, len(picked)),
                                transform=lambda c: pipeline.center_crop(c, crop))
