"""grain pipelines: shapes, determinism, mixtures, per-process shards, resumable state."""

import pathlib
import sys
import types

import grain
import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from sav_jax.data import pipeline
from sav_jax.data.synthetic import SyntheticConfig

CFG = SyntheticConfig(frames=2, height=16, width=16, num_objects=1, max_disparity=6.0)


def _tagged(tag: int, n: int, t=2, h=16, w=16) -> grain.MapDataset:
  """Clips whose `disparity[0, 0, 0]` is `tag * 1000 + index` (identifiable)."""

  def make(i):
    disp = np.full((t, h, w), tag * 1000 + i, np.float32)
    img = np.full((t, h, w, 3), i % 255, np.uint8)
    return {"left": img, "right": img, "disparity": disp, "valid": np.ones((t, h, w), bool)}

  return grain.MapDataset.range(n).map(make)


def _ids(batch):
  return [int(v) for v in batch["disparity"][:, 0, 0, 0]]


def _take(it, k):
  return [next(it) for _ in range(k)]


def test_batches_have_static_shapes_and_dtypes():
  ds = pipeline.make_train_dataset([pipeline.synthetic_source(CFG, 7)], [1.0], batch_size=3,
                                   seed=0, num_threads=1)
  for batch in _take(iter(ds), 4):  # 12 > 7 clips: the stream repeats
    assert batch["left"].shape == batch["right"].shape == (3, 2, 16, 16, 3)
    assert batch["left"].dtype == np.uint8 and batch["valid"].dtype == bool
    assert batch["disparity"].shape == (3, 2, 16, 16) and batch["disparity"].dtype == np.float32


def test_epochs_are_reshuffled_permutations():
  ds = pipeline.make_train_dataset([_tagged(0, 10)], [1.0], batch_size=5, seed=4, num_threads=1)
  ids = sum((_ids(b) for b in _take(iter(ds), 4)), [])
  assert sorted(ids[:10]) == list(range(10)) and sorted(ids[10:]) == list(range(10))
  assert ids[:10] != ids[10:] and ids[:10] != list(range(10))


def test_same_seed_same_stream_other_seed_other_stream():
  make = lambda seed: pipeline.make_train_dataset([_tagged(0, 50)], [1.0], batch_size=4,
                                                  seed=seed, num_threads=2)
  a, b, c = (sum((_ids(x) for x in _take(iter(make(s)), 3)), []) for s in (1, 1, 2))
  assert a == b and a != c


def test_neighbouring_seeds_share_no_epoch_order():
  """grain shuffles epoch e with `seed + e`: seed s + 1's first epoch was seed s's second
  (a seed sweep shared all but one epoch's clip order)."""
  def epochs(seed, n=12, k=3):
    ds = pipeline.make_train_dataset([_tagged(0, n)], [1.0], batch_size=n, seed=seed,
                                     num_threads=1)
    return [_ids(b) for b in _take(iter(ds), k)]

  a, b = epochs(0), epochs(1)
  assert all(sorted(e) == list(range(12)) for e in a + b)
  assert not {tuple(e) for e in a} & {tuple(e) for e in b}
  seeds = {pipeline.stream_seed(s, i, p) for s in (0, 1, 2**32 - 1) for i in (0, 1)
           for p in ("shuffle", "augment")}
  assert len(seeds) == 12 and all(0 <= v < 2**32 for v in seeds)


def test_seeds_up_to_two_to_the_32_with_several_augmented_sources():
  # The per-source seeds wrap into grain's [0, 2**32): the largest seed works with a
  # transform on each of two sources (grain refused a derived seed the user never gave).
  tf = lambda clip, rng: pipeline.as_example(clip)
  it = iter(pipeline.make_train_dataset([_tagged(1, 4), _tagged(2, 4)], [1.0, 1.0], batch_size=2,
                                        seed=2**32 - 1, transforms=[tf, tf], num_threads=1))
  assert len(_ids(next(it))) == 2
  for seed in (2**32, -1, 1.5):
    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*32\)"):
      pipeline.make_train_dataset([_tagged(1, 4)], [1.0], batch_size=2, seed=seed)


def test_counts_are_integers_in_range():
  # (worker_count=-1 acted as 0; a float count failed in grain with a TypeError)
  for bad in ({"batch_size": 0}, {"batch_size": 2.0}, {"worker_count": -1},
              {"num_threads": 1.5}, {"prefetch": -1}):
    name, value = next(iter(bad.items()))
    with pytest.raises(ValueError, match=rf"{name} must be an integer >= [01], got {value}"):
      pipeline.make_train_dataset([_tagged(1, 4)], [1.0], seed=0, **{"batch_size": 2, **bad})
  assert len(pipeline.fixed_clips(_tagged(1, 4), np.int64(2))) == 2  # numpy integers count
  assert pipeline.eval_batches(pipeline.fixed_clips(_tagged(1, 4), 3), np.int32(2))[1][1] == 1


def test_processes_split_one_global_stream():
  # Each process takes every third element of the one stream a single process would read:
  # together they read each epoch once, in the single-process order.
  def stream(p, count, n):
    ds = pipeline.make_train_dataset([_tagged(0, 12)], [1.0], batch_size=1, seed=0,
                                     process_index=p, process_count=count, num_threads=1)
    return [_ids(b)[0] for b in _take(iter(ds), n)]

  single = stream(0, 1, 24)
  parts = [stream(p, 3, 8) for p in range(3)]
  assert [parts[k % 3][k // 3] for k in range(24)] == single
  assert sorted(single[:12]) == sorted(single[12:]) == list(range(12))
  with pytest.raises(ValueError, match="process_index 3 not in"):
    stream(3, 3, 1)


def test_processes_draw_independent_augmentations():
  # The random transform's draws at one step differ between processes (they used to be the
  # same on every process: each shuffled and augmented its own slice with the same seeds).
  def draw(clip, rng):
    ex = pipeline.as_example(clip)
    ex["disparity"] = np.full_like(ex["disparity"], rng.uniform())
    return ex

  first = []
  for p in range(4):
    ds = pipeline.make_train_dataset([_tagged(0, 16)], [1.0], batch_size=2, seed=0,
                                     transforms=[draw], process_index=p, process_count=4,
                                     num_threads=1)
    first.append(tuple(next(iter(ds))["disparity"][:, 0, 0, 0]))
  assert len(set(first)) == 4


@pytest.mark.parametrize("mode,expected", [("ratio", (0.75, 0.25)), ("concat", (0.5, 0.5))])
def test_mixture_proportions(mode, expected):
  # 30 clips with weight 3 vs 90 clips with weight 1.
  ds = pipeline.make_train_dataset([_tagged(1, 30), _tagged(2, 90)], [3.0, 1.0], batch_size=8,
                                   seed=0, mode=mode, num_threads=1)
  tags = np.array(sum((_ids(b) for b in _take(iter(ds), 50)), [])) // 1000
  np.testing.assert_allclose([np.mean(tags == 1), np.mean(tags == 2)], expected, atol=0.02)


def test_mixture_is_an_even_interleaving_of_rounded_shares():
  # README, Training: any run of n clips holds n x share of each source to within about one
  # clip, the shares as grain rounds them (the smallest to 100: 0.3/0.7 drawn as 100/233).
  ds = pipeline.make_train_dataset([_tagged(1, 5, h=1, w=1), _tagged(2, 5, h=1, w=1)],
                                   [3.0, 7.0], batch_size=10, seed=0, num_threads=1)
  first = np.array(sum((_ids(b) for b in _take(iter(ds), 100)), [])) // 1000 == 1  # 1000 clips
  for n in (8, 10, 64):
    runs = np.convolve(first, np.ones(n), "valid")
    assert np.abs(runs - 0.3 * n).max() < 1.5, n
  assert abs(np.mean(first) / 0.3 - 1) < 0.01  # (rounded by grain: within 1%)


def test_mixture_weights_validation():
  assert pipeline.mixture_weights([10, 30], [1, 1], "concat") == [0.25, 0.75]
  with pytest.raises(ValueError, match="mixing mode"):
    pipeline.mixture_weights([1], [1], "sum")
  with pytest.raises(ValueError, match="one weight per source"):
    pipeline.mixture_weights([1, 2], [1], "ratio")
  for weights in ([1, 0], [float("nan"), 1], [float("inf"), 1], [-1, 2]):
    with pytest.raises(ValueError, match="must be finite and > 0"):
      pipeline.mixture_weights([1, 2], weights, "ratio")


def test_a_source_without_clips_says_why(monkeypatch):
  from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(registry, "get_training_clips", lambda *a, **kw: [])
  with pytest.raises(ValueError, match=r"'vkitti2' under 'root' \(split 'train'\) has no clips "
                     r"of 8 frames: its sequences are too short for them \(its training clips "
                     r"take every 1st to 5th frame.*; use fewer frames per clip$"):
    pipeline.registry_source("vkitti2", "root", 8)
  with pytest.raises(ValueError, match=r"too short for them; use fewer frames per clip$"):
    pipeline.registry_source("sceneflow", "root", 8)


def test_bad_pipeline_arguments_are_named():
  a, b = _tagged(1, 4), _tagged(2, 4)
  with pytest.raises(ValueError, match="one transform .* per source, got 1 for 2 sources"):
    pipeline.make_train_dataset([a, b], [1.0, 1.0], batch_size=1, seed=0, transforms=[None])
  clip = a[3]  # frames of value 3
  for crop in ((0, 4), (-4, 10), (17, 4)):
    with pytest.raises(ValueError, match="must be at least 1x1 and at most the frames"):
      pipeline.center_crop(clip, crop)
  for size in (0, -1, 1.5):
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1"):
      pipeline.eval_batches([clip], size)
  with pytest.raises(ValueError, match="no clips"):
    pipeline.eval_batches([], 2)
  with pytest.raises(ValueError, match="num_clips must be an integer >= 1"):
    pipeline.fixed_clips(a, 0)
  # Sources of another frame size in one mixture: the batch names the key and both shapes.
  it = iter(pipeline.make_train_dataset([a, _tagged(2, 4, h=8)], [1.0, 1.0], batch_size=4,
                                        seed=0))
  with pytest.raises(ValueError, match=r"differ in 'left': \(2, (16|8), 16, 3\) uint8 .*same frame "
                     "count and crop"):
    _take(it, 4)
  with pytest.raises(ValueError,
                     match=r"differ in 'left': \(2, 16, 16, 3\) uint8 \(example 0\) and \(3, "):
    pipeline.eval_batches([clip, _tagged(2, 1, t=3)[0]], 2)
  unit = {**clip, "left": clip["left"] / 255.0, "right": clip["right"] / 255.0}
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255") as record:
    pipeline.as_example(unit)
  assert {w.filename for w in record} == {__file__}


class _Sequence:
  """A registry-like sequence whose frames in `broken` do not read (a reader's error)."""

  name, dataset, sparse = "seq", "fake", False

  def __init__(self, broken=()):
    self.broken = set(broken)

  def gather(self, indices):
    for i in indices:
      if i in self.broken:
        raise ValueError(f"/data/seq/{i:04d}.png: cannot decode the image file")
    t = len(indices)
    disp = np.broadcast_to(np.float32(indices[0]), (t, 4, 4)).copy()
    img = np.zeros((t, 4, 4, 3), np.uint8)
    return {"left": img, "right": img, "disparity": disp, "valid": np.ones((t, 4, 4), bool)}


def test_unreadable_clips_stop_or_are_replaced_by_a_drawn_readable_one(caplog):
  seq = _Sequence(broken={2, 3})
  items = [(seq, [i]) for i in range(40)]
  stop = pipeline.clips_source(items)
  assert stop[1]["disparity"][0, 0, 0] == 1
  with pytest.raises(ValueError, match="0002.png: cannot decode") as info:
    stop[2]  # pylint: disable=pointless-statement
  assert pipeline.is_unreadable(info.value)  # what the training's error message tells apart
  skip = pipeline.clips_source(items, skip_unreadable=3)
  with caplog.at_level("WARNING", "sav_jax.data.pipeline"):
    got = [int(skip[i]["disparity"][0, 0, 0]) for i in range(40)]
    assert [int(skip[i]["disparity"][0, 0, 0]) for i in range(40)] == got  # deterministic
  drawn = pipeline._SkippingClips(items, 3)  # pylint: disable=protected-access
  for i in (2, 3):  # a clip drawn at random stands in, not the next one (which shares frames)
    want = next(drawn.stand_in(i, k) for k in range(1, 4) if drawn.stand_in(i, k) not in (2, 3))
    assert got[i] == want and want not in (i - 1, i + 1)
  assert [g for i, g in enumerate(got) if i not in (2, 3)] == [i for i in range(40)
                                                               if i not in (2, 3)]
  warned = [r.getMessage() for r in caplog.records]
  assert len(warned) == 2 and all("skipping an unreadable clip (data.skip_unreadable): fake/seq"
                                  in m for m in warned), warned  # once per clip
  assert "0003.png: cannot decode" in "".join(warned)
  caplog.clear()  # A bad frame in overlapping clips (each frame is in T of them): one warning
  overlapping = pipeline.clips_source([(seq, [i, i + 1, i + 2]) for i in range(38)],
                                      skip_unreadable=3)
  with caplog.at_level("WARNING", "sav_jax.data.pipeline"):
    for i in range(38):
      overlapping[i]  # pylint: disable=pointless-statement
  warned = [r.getMessage() for r in caplog.records]
  assert len(warned) == 2 and "0002.png" in warned[0] and "0003.png" in warned[1], warned
  every = [(_Sequence(broken=range(40)), [i]) for i in range(40)]  # a lost disk
  with pytest.raises(ValueError, match=r"clip 2 and 1 stand-in drawn for it do not read "
                                       r"\(data.skip_unreadable=1 skips no more.*0002.png"):
    pipeline.clips_source(every, skip_unreadable=1)[2]  # pylint: disable=pointless-statement
  no_gt = (types.SimpleNamespace(gather=lambda idx: {"disparity": None}), [0])
  with pytest.raises(ValueError, match="has no ground truth"):  # a config error: not skipped
    pipeline.clips_source([no_gt] + items, skip_unreadable=3)[0]  # pylint: disable=pointless-statement
  with pytest.raises(ValueError, match="skip_unreadable must be an integer >= 0"):
    pipeline.clips_source(items, skip_unreadable=-1)
  batches = pipeline.make_train_dataset([skip], [1.0], batch_size=8, seed=0, num_threads=2)
  ids = sum((_ids(b) for b in _take(iter(batches), 10)), [])  # two epochs through threads
  assert sorted(ids[:40]) == sorted(got) == sorted(ids[40:])


def test_interrupt_and_restore_iterator_state():
  make = lambda: iter(pipeline.make_train_dataset(
      [_tagged(1, 13), pipeline.synthetic_source(CFG, 9)], [2.0, 1.0], batch_size=3, seed=5,
      num_threads=2, prefetch=3))
  reference = _take(make(), 9)
  it = make()
  _take(it, 4)
  state = it.get_state()
  del it  # "interrupted"
  resumed = make()
  resumed.set_state(state)
  for got, want in zip(_take(resumed, 5), reference[4:]):
    jax.tree.map(np.testing.assert_array_equal, got, want)


def test_iterator_state_through_orbax(tmp_path):
  make = lambda: iter(pipeline.make_train_dataset([_tagged(0, 20)], [1.0], batch_size=2,
                                                  seed=9, num_threads=1))
  it = make()
  _take(it, 3)
  with ocp.CheckpointManager(tmp_path, item_names=("data",)) as mngr:
    mngr.save(3, args=ocp.args.Composite(data=grain.checkpoint.CheckpointSave(it)))
    mngr.wait_until_finished()
  want = _ids(next(it))
  fresh = make()
  with ocp.CheckpointManager(tmp_path, item_names=("data",)) as mngr:
    mngr.restore(3, args=ocp.args.Composite(data=grain.checkpoint.CheckpointRestore(fresh)))
  assert _ids(next(fresh)) == want


def test_global_batches_on_the_data_sharding():
  mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("data",))
  sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
  n = len(jax.devices())
  ds = pipeline.make_train_dataset([_tagged(0, 16)], [1.0], batch_size=2 * n, seed=0,
                                   num_threads=1)
  it = pipeline.GlobalBatchIterator(iter(ds), sharding)
  batch = next(it)
  assert batch["left"].shape == (2 * n, 2, 16, 16, 3) and batch["left"].sharding == sharding
  state = it.get_state()
  nxt = jax.device_get(next(it))
  it.set_state(state)
  np.testing.assert_array_equal(jax.device_get(next(it))["disparity"], nxt["disparity"])


def test_eval_batches_pad_to_static_size():
  clips = pipeline.fixed_clips(pipeline.synthetic_source(CFG, 5), 5)
  batches = pipeline.eval_batches(clips, 2)
  assert [n for _, n in batches] == [2, 2, 1]
  assert all(b["left"].shape[0] == 2 for b, _ in batches)
  np.testing.assert_array_equal(batches[-1][0]["left"][1], clips[-1]["left"])


class _FakeSequence:
  """Stands in for `base.StereoSequence`: frame i has disparity i + 1, 20x24 pixels."""

  sparse = False
  dataset, name = "toy", "seq"
  files = {"left": [pathlib.Path(f"/nowhere/seq/left/{i:04d}.png") for i in range(6)]}

  def gather(self, indices):
    n = len(indices)
    disp = np.stack([np.full((20, 24), i + 1.0, np.float32) for i in indices])
    img = np.random.default_rng(0).integers(0, 255, (n, 20, 24, 3)).astype(np.uint8)
    return {"left": img, "right": img.copy(), "disparity": disp, "valid": disp > 0}


def test_registry_source_and_official_augmentation(monkeypatch):
  """The real-data path with a stand-in registry and the project's augmentation."""
  import sav_jax.data as data_pkg  # pylint: disable=g-import-not-at-top
  registry = types.ModuleType("sav_jax.data.registry")
  registry.get_training_clips = lambda dataset, root, n, split="train", seed=0: [
      (_FakeSequence(), [s + k for k in range(n)]) for s in range(0, 6 - n + 1)]
  monkeypatch.setitem(sys.modules, "sav_jax.data.registry", registry)
  monkeypatch.setattr(data_pkg, "registry", registry, raising=False)
  src = pipeline.registry_source("toy", "/nowhere", 3)
  assert len(src) == 4 and src[1]["disparity"][:, 0, 0].tolist() == [2.0, 3.0, 4.0]
  assert src[1]["sparse"] is False
  assert src[1][pipeline.ORIGIN] == ("toy/seq, frames [1, 2, 3] (first left image "
                                     f"{pathlib.Path('/nowhere/seq/left/0001.png')})")
  # an augmentation error names the clip (which dataset of a mixture, which frames)
  too_big = pipeline.Augment((32, 32), (("spatial_prob", 0.0),))
  with pytest.raises(ValueError, match=r"^toy/seq, frames \[0, 1, 2\] \(first left image "
                     r".*0000\.png\): cannot crop \(32, 32\) from \(20, 24\) frames"):
    too_big(src[0], np.random.default_rng(0))
  augment = pipeline.Augment((16, 16), (("eraser_size", [2, 4]),))
  ds = pipeline.make_train_dataset([src], [1.0], batch_size=2, seed=0, num_threads=1,
                                   transforms=[augment])
  batch = next(iter(ds))
  assert batch["left"].shape == (2, 3, 16, 16, 3) and batch["left"].dtype == np.uint8
  assert batch["valid"].dtype == bool and batch["disparity"].shape == (2, 3, 16, 16)
  again = next(iter(ds))  # augmentation is seeded by (seed, index): reproducible
  jax.tree.map(np.testing.assert_array_equal, batch, again)
  crop = pipeline.center_crop(src[0], (16, 16))
  assert crop["left"].shape == (3, 16, 16, 3)


def test_as_example_conversions():
  """Float frames are rounded to the nearest grey level, a float mask is valid from 0.5,
  `[T, H, W, 1]` GT is squeezed, and 0..1 frames (maximum exactly 1) are warned about."""
  left = np.array([10.6, 10.4, 300.0, -3.0], np.float32).reshape(1, 1, 4, 1).repeat(3, -1)
  clip = {"left": left, "right": left, "disparity": np.full((1, 1, 4, 1), 2.0, np.float32),
          "valid": np.array([0.3, 0.5, 0.7, 0.0], np.float32).reshape(1, 1, 4)}
  ex = pipeline.as_example(clip)
  assert ex["left"].dtype == np.uint8 and ex["left"][0, 0, :, 0].tolist() == [11, 10, 255, 0]
  assert ex["valid"].dtype == bool and ex["valid"][0, 0].tolist() == [False, True, True, False]
  assert ex["disparity"].shape == (1, 1, 4) and set(ex) == set(pipeline.EXAMPLE_KEYS)
  unit = np.ones((1, 1, 4, 3), np.float32)  # a 0..1 image: white is exactly 1.0
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255"):
    pipeline.as_example({**clip, "left": unit, "right": unit})
  with pytest.raises(ValueError, match="left/right must be .* of equal shape"):
    pipeline.as_example({**clip, "right": left[:, :, :3]})
  # integer frames beyond 8 bits (a 16-bit source of your own) were clipped to white
  deep = np.full(left.shape, 60000, np.uint16)
  deep[0, 0, 0] = 0
  with pytest.raises(ValueError, match=r"right frames of dtype uint16 with values in 0\.\.60000: "
                                       r"the pipeline expects 8-bit RGB, 0\.\.255"):
    pipeline.as_example({**clip, "left": np.zeros_like(left, np.uint8), "right": deep})
  small = pipeline.as_example({**clip, "left": np.full_like(left, 7, np.int64),
                               "right": np.full_like(left, 255, np.uint16)})
  assert small["left"].dtype == np.uint8 and small["right"].max() == 255  # in range: fine
  for bad in (np.nan, np.inf):  # (NaN was cast to 0 and inf clipped to 255, silently)
    odd = left.copy()
    odd[0, 0, 1, 2] = bad
    with pytest.raises(ValueError, match="right frames hold NaN or infinite values"):
      pipeline.as_example({**clip, "right": odd})


class _SparseSequence(_FakeSequence):
  sparse = True


def test_loaded_clips_keep_their_frame_order_and_sparse_flag():
  # SceneFlow's time-reversed clips are index lists in descending order: loaded as given.
  items = [(_FakeSequence(), [4, 3, 2]), (_SparseSequence(), [0, 1, 2])]
  for src in (pipeline.clips_source(items), pipeline.clips_source(items, skip_unreadable=2)):
    assert src[0]["disparity"][:, 0, 0].tolist() == [5.0, 4.0, 3.0]
    assert src[0]["sparse"] is False and src[1]["sparse"] is True  # sparse augmentation


class _NegativeSequence(_FakeSequence):
  """A reader of your own that returns the official loaders' internal -d for frames >= 2
  (a few positive pixels in them, and a few negative ones in the others)."""

  files = {**_FakeSequence.files,
           "left_gt": [pathlib.Path(f"/nowhere/seq/disparity/{i:04d}.npy") for i in range(6)]}

  def gather(self, indices):
    clip = super().gather(indices)
    for t, i in enumerate(indices):
      clip["disparity"][t] *= -1 if i >= 2 else 1
      clip["disparity"][t, 0, :3] *= -1  # a minority of the other sign
    clip["valid"] = clip["disparity"] != 0
    return clip


def test_a_clip_of_negative_ground_truth_is_refused_naming_the_frame_and_file():
  # Dense clips count any non-zero value below 512 px as valid: -d trained silently against
  # the model's positive disparities.
  seq = _NegativeSequence()
  for skip in (0, 2):  # a convention error, not an unreadable file: never skipped through
    src = pipeline.clips_source([(seq, [0, 1]), (seq, [1, 3, 4])], skip_unreadable=skip)
    assert src[0]["disparity"][:, 5, 5].tolist() == [1.0, 2.0]  # a few negative pixels: fine
    with pytest.raises(ValueError, match=(
        r"toy/seq, frames \[1, 3, 4\] \(first left image .*left/0001.png\): the ground truth "
        r"of frame 3 \(.*disparity/0003.npy\) is negative at 99% of its valid pixels "
        r"\(min -4 px\): .* positive .*negate it")):
      src[1]  # pylint: disable=pointless-statement


class _MaskedSequence(_FakeSequence):
  """A dense reader of your own that marks a band invalid and leaves -1 (or a fill of 7)
  there; the top rows carry 600 px, invalid by the official rule, which stays as it is."""

  def gather(self, indices):
    clip = super().gather(indices)
    clip["disparity"][:, 8:12] = np.float32([-1, 7, 7, 7])[:, None]
    clip["disparity"][:, :2] = 600.0
    clip["valid"] = np.ones_like(clip["valid"])
    clip["valid"][:, 8:12] = False
    clip["valid"][:, :2] = False
    return clip


def test_a_dense_readers_invalid_pixels_stay_out_of_training():
  # The dense augmentation recomputes the mask from the disparity (official), so the -1 and
  # the 7s of the band, which the reader marked invalid, were trained on.
  clip = pipeline.clips_source([(_MaskedSequence(), [0, 1])])[0]
  assert (clip["disparity"][:, 8:12] == 0).all()
  assert (clip["disparity"][:, :2] == 600).all() and (clip["disparity"][:, 2:8] > 0).all()
  # scale 1 (the crop + 8 px is the frame's height), a 12-row crop: rows 8..11 are in it
  identity = (("scale_range", (0.0, 0.0)), ("stretch_prob", 0.0), ("photometric", False),
              ("eraser_prob", 0.0), ("yjitter", False))
  for seed in range(4):
    out = pipeline.Augment((12, 16), identity)(clip, np.random.default_rng(seed))
    assert set(np.unique(out["disparity"][out["valid"]])) == {1.0, 2.0}  # frames 0 and 1
    assert ((~out["valid"]).sum(axis=(1, 2)) >= 4 * 16).all()  # the band's rows at least
  sparse = pipeline.clips_source([(type("S", (_MaskedSequence,), {"sparse": True})(), [0])])[0]
  assert (sparse["disparity"][:, 8] == -1).all()  # a sparse mask is carried: left as read


def test_masks_of_clip_dicts_and_synthetic_clips_stay_out_of_training():
  # Clips not read by a sequence (a clip dict given to clips_source, synthetic_source's
  # occluded pixels): the dense augmentation recomputed their masks as all valid.
  clip = {"left": np.zeros((2, 16, 16, 3), np.uint8), "right": np.zeros((2, 16, 16, 3), np.uint8),
          "disparity": np.full((2, 16, 16), 3.0, np.float32), "valid": np.ones((2, 16, 16), bool)}
  clip["disparity"][:, :, :8], clip["valid"][:, :, :8] = 7.0, False  # no ground truth: a fill
  identity = (("spatial_prob", 0.0), ("photometric", False), ("eraser_prob", 0.0),
              ("yjitter", False))
  for seed in range(3):
    out = pipeline.Augment((8, 12), identity)(pipeline.clips_source([clip])[0],
                                              np.random.default_rng(seed))
    assert (out["disparity"][out["valid"]] == 3).all() and (~out["valid"]).any()
  assert (clip["disparity"][:, :, :8] == 7).all()  # the caller's arrays are left as they are
  weights = {**clip, "valid": np.where(clip["valid"], np.float32(0.9), np.float32(0.3))}
  out = pipeline.Augment((8, 12), identity)(weights, np.random.default_rng(0))
  assert (out["disparity"][out["valid"]] == 3).all()  # a weight of 0.3 is no ground truth
  synthetic = pipeline.synthetic_source(CFG, 1)[0]
  assert not synthetic["valid"].all()
  out = pipeline.Augment((16, 16), identity)(synthetic, np.random.default_rng(0))
  np.testing.assert_array_equal(out["valid"], synthetic["valid"])


def test_stand_ins_are_other_clips_drawn_per_index():
  drawn = pipeline._SkippingClips([None] * 3, 5)  # pylint: disable=protected-access
  for i in range(3):  # never the unreadable clip itself (a wasted try)
    assert all(drawn.stand_in(i, k) in {0, 1, 2} - {i} for k in range(1, 30))
  many = pipeline._SkippingClips([None] * 40, 1)  # pylint: disable=protected-access
  # drawn for each clip: neighbouring unreadable clips do not all take one stand-in
  assert len({many.stand_in(i, 1) for i in range(40)}) > 10


def test_augment_refuses_an_output_of_another_size():
  clip = pipeline.clips_source([(_FakeSequence(), [0, 1])])[0]
  augment = pipeline.Augment((16, 16), (("crop_size", (8, 8)), ("spatial_prob", 0.0)))
  with pytest.raises(ValueError, match=r"produced \(8, 8\), expected the crop \(16, 16\)"):
    augment(clip, np.random.default_rng(0))
  # a config file's lists are the config's tuples (compared with the defaults by the trainer)
  assert pipeline.Augment((16, 16), (("eraser_size", [2, 4]),)).augment_config().eraser_size == (
      2, 4)


def test_center_crop_takes_the_central_window():
  h, w = 7, 10
  yx = np.arange(h * w, dtype=np.float32).reshape(1, h, w)
  clip = {"left": np.zeros((1, h, w, 3), np.uint8), "right": np.zeros((1, h, w, 3), np.uint8),
          "disparity": yx, "valid": np.ones((1, h, w), bool)}
  crop = pipeline.center_crop(clip, (3, 4))  # rows 2..4, columns 3..6
  np.testing.assert_array_equal(crop["disparity"][0],
                                [[23, 24, 25, 26], [33, 34, 35, 36], [43, 44, 45, 46]])
  assert crop["left"].shape == (1, 3, 4, 3) and crop["valid"].shape == (1, 3, 4)


def test_mixed_sources_are_shuffled_independently():
  ds = pipeline.make_train_dataset([_tagged(1, 12), _tagged(2, 12)], [1.0, 1.0], batch_size=8,
                                   seed=0, num_threads=1)
  ids = np.array(sum((_ids(b) for b in _take(iter(ds), 6)), []))
  a, b = ids[ids // 1000 == 1] % 1000, ids[ids // 1000 == 2] % 1000
  n = min(len(a), len(b), 12)
  assert n >= 8 and a[:n].tolist() != b[:n].tolist()  # not one permutation for both


def test_each_source_gets_its_own_transform():
  # e.g. synthetic clips (None: used as generated) mixed with an augmented dataset
  def mark(clip, rng):
    del rng
    ex = pipeline.as_example(clip)
    ex["valid"] = np.zeros_like(ex["valid"])
    return ex

  ds = pipeline.make_train_dataset([_tagged(1, 6), _tagged(2, 6)], [1.0, 1.0], batch_size=8,
                                   seed=0, transforms=[mark, None], num_threads=1)
  for batch in _take(iter(ds), 3):
    tags = batch["disparity"][:, 0, 0, 0] // 1000
    assert (batch["valid"][:, 0, 0, 0] == (tags == 2)).all()


def test_stacking_refuses_other_dtypes_or_keys():
  a = _tagged(1, 1)[0]
  with pytest.raises(ValueError, match=r"differ in 'disparity': \(2, 16, 16\) float32 .* float64"):
    pipeline.stack_examples([a, {**a, "disparity": a["disparity"].astype(np.float64)}])
  with pytest.raises(ValueError, match="different keys"):
    pipeline.stack_examples([a, {**a, "depth": a["disparity"]}])


def test_clips_digest_tells_sequences_apart():
  # a sequence replaced by another of the same length: a resumed run is warned
  a, b = types.SimpleNamespace(name="a"), types.SimpleNamespace(name="b")
  assert pipeline.clips_digest([(a, [0, 1])]) != pipeline.clips_digest([(b, [0, 1])])
  # a resumed run holds other objects for the same sequences: same names, same digest;
  # the clips' order is part of it
  again = types.SimpleNamespace(name="a")
  assert pipeline.clips_digest([(a, [0, 1])]) == pipeline.clips_digest([(again, [0, 1])])
  assert (pipeline.clips_digest([(a, [0, 1]), (b, [0, 1])])
          != pipeline.clips_digest([(b, [0, 1]), (a, [0, 1])]))


def test_fixed_clips_are_the_first_ones_and_never_wrap():
  # (a grain MapDataset wraps indices past its end: clip 3 of 3 clips would be clip 0)
  assert [int(c["disparity"][0, 0, 0]) for c in pipeline.fixed_clips(_tagged(0, 5), 3)] == [
      0, 1, 2]
  with pytest.raises(ValueError, match="validation set has 3 clips, 4 requested"):
    pipeline.fixed_clips(_tagged(0, 3), 4)


def _folder_layout(root, frames):
  """One sequence `test/s1` of the "folder" dataset: 4x6 PNG frames, no ground truth."""
  import cv2  # pylint: disable=import-outside-toplevel
  for side in ("left", "right"):
    (root / "test/s1" / side).mkdir(parents=True)
    for i in range(frames):
      assert cv2.imwrite(str(root / "test/s1" / side / f"{i:04d}.png"),
                         np.full((4, 6, 3), i, np.uint8))


def test_registry_clips_are_consecutive_or_strided_by_the_seed(tmp_path):
  _folder_layout(tmp_path, frames=15)
  consecutive = pipeline.registry_clips("folder", tmp_path, 2, split="test", consecutive=True)
  assert [c[1] for c in consecutive] == [[s, s + 1] for s in range(0, 14, 2)]  # 0, T, 2T, ...

  def official(seed):  # datasets.md: starts 0, 3, 6; k in 1..5 per start; kept if s + kT < N
    rng, out = np.random.default_rng(seed), []
    for start in range(0, 15, 3):
      k = int(rng.integers(1, 6))
      if start + 2 * k < 15:
        out.append([start, start + k])
    return out

  assert official(1) != official(0)
  for seed in (0, 1):
    clips = pipeline.registry_clips("folder", tmp_path, 2, split="test", seed=seed)
    assert [c[1] for c in clips] == official(seed)


def test_grain_workers_outlive_a_sigterm_to_the_process_group():
  """Schedulers send SIGTERM to every process of a job, a terminal's Ctrl-C SIGINT: the
  training process then finishes its step and saves a checkpoint, for which it still reads
  from its grain workers (they died on the signal before: the read failed and no checkpoint
  was saved)."""
  import os  # pylint: disable=import-outside-toplevel
  import signal  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import time  # pylint: disable=import-outside-toplevel
  from absl import flags  # pylint: disable=import-outside-toplevel
  if not flags.FLAGS.is_parsed():  # grain's workers read absl flags (`python -m train` parses)
    flags.FLAGS.mark_as_parsed()
  src = pipeline.synthetic_source(SyntheticConfig(frames=2, height=16, width=16,
                                                  max_disparity=8.0), 20)
  it = iter(pipeline.make_train_dataset([src], [1.0], batch_size=2, seed=0, num_threads=1,
                                        worker_count=1))
  def spawned():  # this process's multiprocessing children (not the suite's other jobs)
    ps = subprocess.run(["ps", "-ww", "-o", "pid=,args=", "--ppid", str(os.getpid())],
                        capture_output=True, text=True, check=False).stdout
    return {int(line.split()[0]) for line in ps.splitlines() if "spawn_main" in line}

  before = spawned()
  next(it)
  workers = sorted(spawned() - before)
  assert workers
  for pid in workers:
    os.kill(pid, signal.SIGTERM)
    os.kill(pid, signal.SIGINT)
  time.sleep(1.0)
  for _ in range(12):  # more batches than the workers had buffered
    assert next(it)["left"].shape == (2, 2, 16, 16, 3)
  it.close() if hasattr(it, "close") else None  # pylint: disable=expression-not-assigned


# (no absl flag parsing: the pipeline starts grain's workers from a plain script too)
_ORPHAN_SCRIPT = """
import sys
from sav_jax.data import pipeline
from sav_jax.data.synthetic import SyntheticConfig
src = pipeline.synthetic_source(SyntheticConfig(frames=2, height=16, width=16,
                                                max_disparity=8.0), 20)
it = iter(pipeline.make_train_dataset([src], [1.0], batch_size=2, seed=0, num_threads=1,
                                      worker_count=1))
next(it)
print("ready", flush=True)
sys.stdin.read()
"""


def test_grain_workers_end_with_a_killed_training_process(tmp_path):
  """A training process that is SIGKILLed (or taken by the out-of-memory killer) never stops
  its grain workers; they ignore SIGTERM (above), so orphans would outlive `kill` too: each
  ends itself once its parent is gone."""
  import os  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  import time  # pylint: disable=import-outside-toplevel
  root = pathlib.Path(__file__).resolve().parents[2]
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]),
             JAX_PLATFORMS="cpu")
  proc = subprocess.Popen([sys.executable, "-c", _ORPHAN_SCRIPT], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True,
                          cwd=tmp_path)
  try:
    assert proc.stdout.readline().strip() == "ready"
    ps = subprocess.run(["ps", "-ww", "-o", "pid=,args=", "--ppid", str(proc.pid)],
                        capture_output=True, text=True, check=False).stdout
    workers = [int(line.split()[0]) for line in ps.splitlines() if "spawn_main" in line]
    assert workers
  finally:
    proc.kill()  # SIGKILL: grain's stop never runs
    proc.wait()
  deadline = time.time() + 20
  alive = list(workers)
  while alive and time.time() < deadline:
    time.sleep(0.2)
    alive = [pid for pid in alive if pathlib.Path(f"/proc/{pid}").exists()
             and "zombie" not in _proc_state(pid)]
  for pid in alive:  # (a failure leaves no orphan behind)
    os.kill(pid, 9)
  assert not alive, f"grain workers {alive} outlived their killed parent"


def _proc_state(pid: int) -> str:
  try:
    return pathlib.Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0]
  except (OSError, IndexError):
    return "zombie"  # gone meanwhile


def test_as_example_keeps_each_view_and_gives_the_pipelines_dtypes():
  # Each view as given (the right view is not the left one), a float64 disparity as float32,
  # a [T, H, W, 1] mask (as a [T, H, W, 1] disparity) as [T, H, W] bool thresholded at 0.5;
  # a mask of another size, or integer frames below 0, are refused.
  left = np.full((2, 1, 3, 3), 10, np.int64)
  right = np.full((2, 1, 3, 3), 20, np.int64)
  valid = np.array([0.0, 0.5, 1.0, 1.0, 0.2, 0.0], np.float32).reshape(2, 1, 3, 1)
  clip = {"left": left, "right": right, "disparity": np.full((2, 1, 3), 1.5, np.float64),
          "valid": valid}
  ex = pipeline.as_example(clip)
  assert ex["left"].dtype == ex["right"].dtype == np.uint8
  assert (ex["left"] == 10).all() and (ex["right"] == 20).all()
  assert ex["disparity"].dtype == np.float32 and (ex["disparity"] == 1.5).all()
  assert ex["valid"].shape == (2, 1, 3) and ex["valid"].dtype == bool
  assert ex["valid"].tolist() == [[[False, True, True]], [[True, False, False]]]
  for key in ("disparity", "valid"):  # [T, H, W] of the frames, each
    with pytest.raises(ValueError, match=rf"{key} \(2, 1, 2\).* do not match the images"):
      pipeline.as_example({**clip, key: np.ones((2, 1, 2), clip[key].dtype)})
  with pytest.raises(ValueError, match=r"right frames of dtype int64 with values in 20\.\.256"):
    pipeline.as_example({**clip, "right": right + (np.arange(3) == 2) * 236})  # 8 bits: <= 255
  below = np.full(left.shape, 5, np.int16)
  below[1, 0, 2, 1] = -1
  with pytest.raises(ValueError, match=r"left frames of dtype int16 with values in -1\.\.5"):
    pipeline.as_example({**clip, "left": below})


def test_global_batches_keep_the_local_dtypes_and_values():
  # The train step receives uint8 frames, float32 disparities and a bool mask, as stacked on
  # the host (a float copy of the frames is 4x the transfer). The copy is allowed under any
  # transfer guard: on one process it is an explicit one, which "disallow" lets through, so
  # "disallow_explicit" tells whether `to_global` allows it (as it must for a run of several
  # processes under "disallow", where the placement counts as implicit).
  mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("data",))
  sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
  n = len(jax.devices())
  clips = [_tagged(3, 2 * n)[i] for i in range(2 * n)]
  local = pipeline.stack_examples(clips)
  with jax.transfer_guard("disallow_explicit"):
    batch = pipeline.to_global(local, sharding)
  assert {k: v.dtype for k, v in batch.items()} == {
      "left": np.uint8, "right": np.uint8, "disparity": np.float32, "valid": np.bool_}
  for k, v in batch.items():
    assert v.sharding == sharding and v.shape == local[k].shape
    np.testing.assert_array_equal(np.asarray(v), local[k])
  assert _ids(jax.device_get(batch)) == [3000 + i for i in range(2 * n)]


def test_the_process_share_defaults_to_jaxs_process_index_and_count(monkeypatch):
  # Without process_index/process_count (the trainer's multi-host default), process 1 of 2
  # reads the odd elements of the one global stream, not process 0's share.
  make = lambda **kw: iter(pipeline.make_train_dataset([_tagged(0, 12)], [1.0], batch_size=3,
                                                       seed=2, num_threads=1, **kw))
  single = sum((_ids(b) for b in _take(make(process_index=0, process_count=1), 4)), [])
  monkeypatch.setattr(jax, "process_index", lambda: 1)
  monkeypatch.setattr(jax, "process_count", lambda: 2)
  assert sum((_ids(b) for b in _take(make(), 2)), []) == single[1::2]


def test_stream_seeds_are_the_recorded_derivation():
  # Checkpoints record the derivation (pipeline.SEEDING = 2): words (seed, source, purpose
  # 0 = shuffle / 1 = augment) of a numpy SeedSequence, its first uint32. Another derivation
  # gives a resumed run other clip orders, so it must come with another SEEDING.
  assert pipeline.SEEDING == 2
  for seed, source, purpose, word in ((0, 0, "shuffle", 0), (7, 1, "augment", 1),
                                      (2**32 - 1, 3, "shuffle", 0)):
    want = int(np.random.SeedSequence([seed, source, word]).generate_state(1, np.uint32)[0])
    assert pipeline.stream_seed(seed, source, purpose) == want


def test_center_crop_rounds_odd_margins_down_and_may_take_the_whole_frame():
  # margins of 5 rows and 7 columns: 2 rows above, 3 columns left (floor of half)
  h, w = 8, 11
  yx = np.arange(h * w, dtype=np.float32).reshape(1, h, w)
  clip = {"left": np.zeros((1, h, w, 3), np.uint8), "right": np.zeros((1, h, w, 3), np.uint8),
          "disparity": yx, "valid": np.ones((1, h, w), bool)}
  crop = pipeline.center_crop(clip, (3, 4))
  np.testing.assert_array_equal(crop["disparity"][0],
                                [[25, 26, 27, 28], [36, 37, 38, 39], [47, 48, 49, 50]])
  for full in ((8, 11), (8, 3), (2, 11)):  # a crop the size of the frames (in either axis)
    assert pipeline.center_crop(clip, full)["disparity"].shape == (1, *full)
  for big in ((9, 4), (3, 12)):  # larger than the frames in either axis
    with pytest.raises(ValueError, match="at most the frames"):
      pipeline.center_crop(clip, big)


def test_eval_batches_hold_the_clips_in_order_then_the_padding():
  # num_real_clips counts the first rows: the real clips come first, in order, then copies of
  # the last one; extra keys of a loaded clip (its origin) stay out of the batch.
  clips = [dict(_tagged(0, 5)[i], origin=f"clip {i}") for i in range(5)]
  batches = pipeline.eval_batches(clips, 3)
  assert [(_ids(b), n) for b, n in batches] == [([0, 1, 2], 3), ([3, 4, 4], 2)]
  assert all(set(b) == set(pipeline.EXAMPLE_KEYS) for b, _ in batches)


def test_dense_masks_are_honoured_for_the_right_view_too():
  # A pixel the reader marks invalid is set to 0 where the official rule would count it
  # (d != 0 and |d| < 512): -1 and 7 go, 600 (invalid by the rule) and valid pixels stay.
  disp = np.array([3.0, -1.0, 7.0, 600.0], np.float32).reshape(1, 1, 4)
  valid = np.array([True, False, False, False]).reshape(1, 1, 4)
  clip = {"disparity": disp.copy(), "valid": valid, "right_disparity": disp.copy() + 1,
          "right_valid": valid}
  pipeline.honour_dense_masks(clip)
  assert clip["disparity"].ravel().tolist() == [3.0, 0.0, 0.0, 600.0]
  assert clip["right_disparity"].ravel().tolist() == [4.0, 0.0, 0.0, 601.0]
  assert clip["disparity"].dtype == np.float32


def test_the_sign_check_refuses_a_majority_of_negative_valid_pixels_only():
  # "most valid pixels negative": a tie is no majority, a valid 0 has no sign, and invalid
  # pixels (a sparse reader's -1 fill) are not counted.
  seq = types.SimpleNamespace(name="s", dataset="d")
  check = lambda d, v: pipeline.check_disparity_sign(
      {"disparity": np.float32(d).reshape(1, 1, 4), "valid": np.array(v).reshape(1, 1, 4)},
      seq, [0])
  check([2, -2, 0, 5], [True, True, False, False])  # one each
  check([1, 0, 0, 0], [True] * 4)  # zeros count for neither sign
  check([1, -1, -1, -1], [True, False, False, False])  # the negatives are invalid
  with pytest.raises(ValueError, match="d/s, frames \\[0\\]: the ground truth of frame 0 is "
                                       "negative at 67% of its valid pixels"):
    check([1, -1, -1, 0], [True] * 4)


class _MissingFiles(_Sequence):
  """A sequence whose frames in `broken` are missing files (the reader's OSError)."""

  def gather(self, indices):
    for i in indices:
      if i in self.broken:
        raise FileNotFoundError(f"/data/seq/{i:04d}.png: no such file")
    return super().gather(indices)


def test_a_missing_file_is_an_unreadable_clip_and_stand_ins_are_distinct_draws():
  items = [(_MissingFiles(broken={5}), [i]) for i in range(40)]
  with pytest.raises(FileNotFoundError, match="0005.png") as info:
    pipeline.clips_source(items)[5]  # pylint: disable=pointless-statement
  assert pipeline.is_unreadable(info.value)  # skipped by data.skip_unreadable, as a ValueError
  assert int(pipeline.clips_source(items, skip_unreadable=1)[5]["disparity"][0, 0, 0]) != 5
  drawn = pipeline._SkippingClips(items, 3)  # pylint: disable=protected-access
  # each try draws again: not the same stand-in three times (one bad clip, three tries)
  assert all(len({drawn.stand_in(i, k) for k in (1, 2, 3)}) > 1 for i in range(40))
  # the tries for a clip are bounded by the other clips there are: 2 stand-ins of 3 clips
  lost = [(_MissingFiles(broken=range(3)), [i]) for i in range(3)]
  with pytest.raises(ValueError, match="clip 0 and 2 stand-ins drawn for it do not read"):
    pipeline.clips_source(lost, skip_unreadable=5)[0]  # pylint: disable=pointless-statement


def test_a_skipping_source_keeps_its_skip_count_in_grain_workers():
  # grain's worker processes get the source pickled
  import pickle  # pylint: disable=import-outside-toplevel
  src = pipeline._SkippingClips([(_Sequence(broken={2}), [i]) for i in range(10)], 2)  # pylint: disable=protected-access
  again = pickle.loads(pickle.dumps(src))
  assert int(again[2]["disparity"][0, 0, 0]) == int(src[2]["disparity"][0, 0, 0]) != 2


def test_a_source_without_a_transform_is_made_examples():
  # transforms=None: `as_example` (the batch gets the pipeline's keys and dtypes, not a
  # loader's float frames, [T, H, W, 1] disparities or extra keys)
  def make(i):
    return {"left": np.full((2, 4, 4, 3), 100.4 + i), "right": np.full((2, 4, 4, 3), 50.0),
            "disparity": np.full((2, 4, 4, 1), i, np.float64), "valid": np.ones((2, 4, 4)),
            "origin": f"clip {i}"}

  ds = pipeline.make_train_dataset([grain.MapDataset.range(4).map(make)], [1.0], batch_size=2,
                                   seed=0, num_threads=1)
  batch = next(iter(ds))
  assert {k: (v.dtype, v.shape) for k, v in batch.items()} == {
      "left": (np.uint8, (2, 2, 4, 4, 3)), "right": (np.uint8, (2, 2, 4, 4, 3)),
      "disparity": (np.float32, (2, 2, 4, 4)), "valid": (np.bool_, (2, 2, 4, 4))}
  assert (batch["left"][:, 0, 0, 0, 0] == 100 + batch["disparity"][:, 0, 0, 0]).all()


def test_augmented_sources_draw_independently():
  # Each source's random map has its own seed: the k-th clip of one source is not jittered
  # as the k-th clip of the other.
  def draw(clip, rng):
    ex = pipeline.as_example(clip)
    ex["disparity"][:, :, 1:] = rng.uniform()  # [.., 0, 0] keeps the clip's tag
    return ex

  ds = pipeline.make_train_dataset([_tagged(1, 8), _tagged(2, 8)], [1.0, 1.0], batch_size=8,
                                   seed=0, transforms=[draw, draw], num_threads=1)
  draws = {1: set(), 2: set()}
  for batch in _take(iter(ds), 2):
    for tag, value in zip(np.array(_ids(batch)) // 1000, batch["disparity"][:, 0, 0, 1]):
      draws[tag].add(float(value))
  assert len(draws[1]) >= 6 and len(draws[2]) >= 6 and not draws[1] & draws[2]


def test_registry_sources_get_the_seed_and_name_the_stride_only_for_strided_clips(monkeypatch):
  from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
  seeds = []
  monkeypatch.setattr(registry, "get_training_clips",
                      lambda *a, seed=0, **kw: seeds.append(seed) or [])
  monkeypatch.setattr(registry, "get_consecutive_clips", lambda *a, **kw: [])
  with pytest.raises(ValueError, match="every 1st to 5th frame"):
    pipeline.registry_source("vkitti2", "root", 8, seed=7)
  assert seeds == [7]  # the official per-start stride draws
  with pytest.raises(ValueError, match=r"too short for them; use fewer frames per clip$"):
    pipeline.registry_source("vkitti2", "root", 8, consecutive=True)  # consecutive: no stride


def test_clips_digest_tells_frame_indices_apart():
  a = types.SimpleNamespace(name="a")
  assert pipeline.clips_digest([(a, [0, 1])]) != pipeline.clips_digest([(a, [1, 2])])


def test_an_augmentation_error_of_a_clip_without_an_origin_is_raised_as_it_is():
  # (a generated clip, or one of your own pipeline: no `origin` to name)
  clip = _tagged(0, 1)[0]
  with pytest.raises(ValueError, match=r"^cannot crop \(32, 32\) from \(16, 16\) frames"):
    pipeline.Augment((32, 32), (("spatial_prob", 0.0),))(clip, np.random.default_rng(0))


def test_augment_gives_only_the_example_keys():
  # A loaded clip carries `sparse` and `origin`, which augment_clip passes through: neither
  # goes into a batch (an array of strings does not go to the devices).
  clip = pipeline.clips_source([(_FakeSequence(), [0, 1])])[0]
  assert {"sparse", pipeline.ORIGIN} <= set(clip)
  out = pipeline.Augment((16, 16))(clip, np.random.default_rng(0))
  assert set(out) == set(pipeline.EXAMPLE_KEYS)


def test_a_stream_needs_a_source():
  with pytest.raises(ValueError, match="need one weight per source, got 0 for 0"):
    pipeline.make_train_dataset([], [], batch_size=1, seed=0)
