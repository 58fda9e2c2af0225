"""Your own stereo videos (`sav_jax.data.stereo_folder`): every frame of each sequence of
`<data-root>/test/<sequence>/{left,right[,disparity]}` (sequences without `disparity/` get
strips, and their predictions with --config.save_predictions=true, no metrics).

    python -m eval --config configs/eval/folder.py --checkpoint CKPT --data-root my_videos
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("folder", split="test")
