"""Fine-tuning on Dynamic Replica + Infinigen SV + Virtual KITTI 2 (the "MIX" recipe).

The official script builds this mixture with `--train_datasets dynamic_replica
infinigen_stereovideo vkitti2`: a concatenation in which Infinigen SV appears three
times, so a dataset's share is (repeats x clips). The released MIX checkpoint's exact
recipe is not in the official repository (not confirmed: the official KITTI Depth loader
has a training split, so the MIX model may have seen KITTI too; add a source for it if so);
everything else is the SceneFlow recipe with 80k steps, starting from the SceneFlow weights
(pass them as init_from: without it, or vda_weights, the run refuses to start).

Usage:
  python -m train --config configs/mixed.py --workdir runs/mix \
      --config.init_from=runs/sceneflow   # a run's WORKDIR: its latest checkpoint's params
"""

import ml_collections

from configs import sceneflow


def get_config() -> ml_collections.ConfigDict:
  c = sceneflow.base_config()
  # Fine-tuning length (official num_steps default and script value).
  c.train.num_steps = 80_000
  # Dynamic Replica once, Infinigen SV three times, VKITTI2 once (official concatenation).
  c.data.sources.dynamic_replica = ml_collections.ConfigDict(
      dict(dataset="dynamic_replica", weight=1.0))
  c.data.sources.infinigen_sv = ml_collections.ConfigDict(
      dict(dataset="infinigen_sv", weight=3.0))
  c.data.sources.vkitti2 = ml_collections.ConfigDict(dict(dataset="vkitti2", weight=1.0))
  # Validate on the Dynamic Replica validation split (centre crops of the training size).
  c.eval.dataset = "dynamic_replica"
  # Split of Dynamic Replica used for validation.
  c.eval.split = "valid"
  return c
