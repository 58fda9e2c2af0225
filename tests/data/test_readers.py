"""Dataset readers and the registry on tiny fakes of every on-disk layout.

Each fake is written with the libraries the real files come from (OpenCV PNG/JPEG,
numpy, h5py, gzip JSON, the Sintel .cam byte layout); decoded disparities, masks and
depth2disp scales are compared value by value with what was written.
"""

import gzip
import json
import logging
import pathlib
import pickle
import re
import shutil
import struct
import warnings

import cv2
import numpy as np
import pytest

import sav_jax.data
from sav_jax.data import base, frame_io, kitti_depth, registry, stereo_folder

H, W = 8, 12


def _rgb(rng):
  return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


def _png(path, img):
  path.parent.mkdir(parents=True, exist_ok=True)
  assert cv2.imwrite(str(path), img[..., ::-1] if img.ndim == 3 else img)


def _mkfile(path, writer, *args):
  path.parent.mkdir(parents=True, exist_ok=True)
  writer(path, *args)


def _stereo(rng, d_dir_l, d_dir_r, names, written, ext=".png"):
  for n in names:
    for folder, side in ((d_dir_l, "left"), (d_dir_r, "right")):
      img = _rgb(rng)
      _png(folder / f"{n}{ext}", img)
      written.setdefault(side, []).append(img)


def _check_images(seq, written):
  for i in range(len(seq)):
    frame = seq[i]
    np.testing.assert_array_equal(frame["left"], written["left"][i])
    np.testing.assert_array_equal(frame["right"], written["right"][i])


def _sceneflow(root, rng, frames=4):
  truth = {}
  for rel in ("FlyingThings3D/{p}/TRAIN/A/0000", "FlyingThings3D/{p}/TEST/B/0001",
              "Monkaa/{p}/a_rain_of_stones_x2", "Driving/{p}/15mm_focallength/scene_forwards/fast"):
    seq_dir = root / rel.format(p="frames_finalpass")
    gt_dir = root / rel.format(p="disparity")
    written = {}
    names = [f"{6 + i:04d}" for i in range(frames)]
    _stereo(rng, seq_dir / "left", seq_dir / "right", names, written)
    for side in ("left", "right"):
      for n in names:
        d = rng.uniform(0.5, 100, (H, W)).astype(np.float32)
        d[0, 0], d[1, 1] = 0.0, 600.0  # invalid by the dense rule
        _mkfile(gt_dir / side / f"{n}.pfm", frame_io.write_pfm, d, side == "left")
        written.setdefault(side + "_d", []).append(d)
    truth[rel.split("/")[0] + "/" + rel.split("{p}/")[1]] = written
  return truth


def test_sceneflow_train_test_values_and_clips(tmp_path):
  truth = _sceneflow(tmp_path, np.random.default_rng(0))
  seqs = registry.get_sequences("sceneflow", tmp_path, "train")
  assert [s.name for s in seqs] == ["FlyingThings3D/TRAIN/A/0000", "Monkaa/a_rain_of_stones_x2",
                                    "Driving/15mm_focallength/scene_forwards/fast"]
  for seq in seqs:
    written = truth[seq.name]
    assert seq.dataset == "sceneflow" and seq.depth2disp_scale is None and not seq.sparse
    _check_images(seq, written)
    seq.with_right_disparity = True
    for i in range(len(seq)):
      f = seq[i]
      np.testing.assert_array_equal(f["disparity"], written["left_d"][i])
      np.testing.assert_array_equal(f["right_disparity"], written["right_d"][i])
      expect = (written["left_d"][i] != 0) & (written["left_d"][i] < 512)
      np.testing.assert_array_equal(f["valid"], expect)
  test = registry.get_sequences("sceneflow", tmp_path, "test")
  assert [s.name for s in test] == ["FlyingThings3D/TEST/B/0001"]
  # One subset, from its own folder too.
  assert len(registry.get_sequences("monkaa", tmp_path / "Monkaa", "train")) == 1
  with pytest.raises(ValueError, match="no split 'test'"):
    registry.get_sequences("driving", tmp_path, "test")
  clips = registry.get_training_clips("flyingthings3d", tmp_path, frames=2)
  # N = 4, T = 2: refs 0, 1 (N - T = 2 left out), each forward then time-reversed.
  assert [c.indices for c in clips] == [[0, 1], [3, 2], [1, 2], [2, 1]]
  assert len(registry.get_training_clips("sceneflow", tmp_path, frames=2)) == 12
  gt = tmp_path / "Monkaa/disparity/a_rain_of_stones_x2/left"
  (gt / "0007.pfm").rename(gt / "0019.pfm")
  with pytest.raises(ValueError, match="stem mismatch.*0007.png.*0008.pfm"):
    registry.get_sequences("monkaa", tmp_path, "train")
  with pytest.raises(FileNotFoundError, match="frames_cleanpass"):
    registry.get_sequences("driving", tmp_path, "train", pass_name="frames_cleanpass")
  with pytest.raises(FileNotFoundError, match="dataset root not found"):
    registry.get_sequences("sceneflow", tmp_path / "nowhere", "train")
  (tmp_path / "a_file").write_text("")
  with pytest.raises(NotADirectoryError, match="dataset root .*a_file is a file, not a folder"):
    registry.get_sequences("sceneflow", tmp_path / "a_file", "train")
  # the folder dataset's root too (was "dataset folder not found", the file being there)
  with pytest.raises(NotADirectoryError, match="dataset folder .*a_file is a file, not a"):
    registry.get_sequences("folder", tmp_path / "a_file", "test")


@pytest.mark.parametrize("dataset", [d for d in registry.DATASETS if d != "folder"])
def test_a_root_without_the_dataset_folder_is_named(tmp_path, dataset):
  """A root that neither holds the dataset's folder nor is it (a typo, the wrong level) was
  reported as some file missing under it, e.g. `ROOT/training/final_left` for Sintel."""
  (tmp_path / "other").mkdir()
  folders = " or ".join(f"{f}/" for f in registry._FOLDERS[dataset])  # pylint: disable=protected-access
  with pytest.raises(FileNotFoundError, match=rf"\({re.escape(str(tmp_path))} holds no "
                     rf"{re.escape(folders)} folder and is not one either: pass the datasets "
                     "folder that holds"):
    registry.get_sequences(dataset, tmp_path, registry.SPLITS[dataset][0])
  # the dataset's own folder, incomplete: what is missing in it, without that hint
  own = tmp_path / registry._FOLDERS[dataset][0]  # pylint: disable=protected-access
  own.mkdir()
  with pytest.raises(FileNotFoundError) as e:
    registry.get_sequences(dataset, own, registry.SPLITS[dataset][0])
  assert "is not one either" not in str(e.value) and str(own) in str(e.value)


@pytest.mark.parametrize("dataset", [d for d in registry.DATASETS if d != "folder"])
def test_a_dataset_folder_linked_to_nothing_is_named(tmp_path, dataset):
  """`data/datasets/<folder>` a link to a missing folder (storage not mounted): the error said
  the root "holds no <folder>/ folder and is not one either", not that the link is broken."""
  folder = registry._FOLDERS[dataset][0]  # pylint: disable=protected-access
  (tmp_path / folder).symlink_to(tmp_path / "unmounted")
  with pytest.raises(FileNotFoundError, match=rf"{re.escape(folder)}: a symbolic link to a "
                     "missing file or folder") as e:
    registry.get_sequences(dataset, tmp_path, registry.SPLITS[dataset][0])
  assert "is not one either" not in str(e.value)


@pytest.mark.parametrize("dataset,split,folder,message", [
    ("sintel_final", "test", "sintel_stereo/training/final_left", "no Sintel sequences in"),
    ("infinigen_sv", "test", "InfinigenStereo/test", "no Infinigen SV scenes in"),
    ("vkitti2", "train", "vkitti2", "no VKITTI2 train sequences under"),
    ("kitti_depth", "train", "kitti_depth/gt_depth", "no KITTI Depth train drives in"),
    ("spring", "test", "Spring/train", "no Spring sequences under"),
    ("south_kensington", "test", "SouthKensington/data",
     "no South Kensington sequences with a camera txt under"),
    ("tartanair", "train", "TartanAir/abandonedfactory/Easy", "no TartanAir train sequences"),
])
def test_a_split_without_sequences_is_an_error_not_an_empty_list(tmp_path, dataset, split,
                                                                 folder, message):
  """The dataset's folders there but empty (an archive not unpacked yet): an empty list would
  be an evaluation or a training mix without that dataset, reported as if complete."""
  (tmp_path / folder).mkdir(parents=True)
  with pytest.raises(FileNotFoundError, match=message):
    registry.get_sequences(dataset, tmp_path, split)


@pytest.mark.parametrize("module", ["sintel", "infinigen", "vkitti2", "kitti_depth", "spring",
                                    "south_kensington", "tartanair"])
def test_a_reader_called_directly_refuses_an_unknown_split(tmp_path, module):
  """`load_sequences` is public: a split it does not have ("valid", DR's name) is refused, not
  read as another split (Sintel and VKITTI2 read their training sequences whatever it was)."""
  reader = getattr(sav_jax.data, module)
  with pytest.raises(ValueError, match=r"split must be one of \(.*\), got 'valid'"):
    reader.load_sequences(tmp_path, "valid")
  if module == "sintel":  # and a pass other than clean or final
    with pytest.raises(ValueError, match=r"Sintel pass must be one of \('clean', 'final'\), "
                                         "got 'albedo'"):
      reader.load_sequences(tmp_path, "test", dstype="albedo")


def test_a_renamed_dataset_folder_missing_a_file_is_not_called_the_wrong_root(tmp_path):
  """A dataset's folder under another name reads as that folder; a file missing in it was
  reported with "(ROOT holds no dynamic_replica_data/ folder and is not one either: pass the
  datasets folder ...)", sending the user to look for a wrong root instead of the file."""
  _dynamic_replica(tmp_path, np.random.default_rng(0), "test", [("seq_a", 3, "ndc_isotropic")])
  _sintel(tmp_path / "s", np.random.default_rng(1))
  dr, sintel = tmp_path / "DR", tmp_path / "Sintel"
  (tmp_path / "dynamic_replica_data").rename(dr)
  (tmp_path / "s" / "sintel_stereo").rename(sintel)
  assert len(registry.get_sequences("dynamic_replica", dr, "test", max_frames=None)) == 1
  assert len(registry.get_sequences("sintel_final", sintel, "test")) == 2
  (dr / "test" / "seq_a" / "depths" / "right_000002.geometric.png").unlink()
  shutil.rmtree(sintel / "training" / "camdata_left" / "cave_2")
  for dataset, root, missing in (
      ("dynamic_replica", dr, "depths/right_000002.geometric.png"),
      ("sintel_final", sintel, "camdata_left/cave_2")):
    with pytest.raises(FileNotFoundError, match=re.escape(missing)) as e:
      registry.get_sequences(dataset, root, "test", max_frames=None)
    assert "is not one either" not in str(e.value)
  # a datasets folder (another dataset's folder in it, read as a sequence) keeps the hint
  (tmp_path / "kitti_depth").mkdir()
  (tmp_path / "kitti_depth" / "README.txt").write_text("Intrinsic: [[1 0 0] [0 1 0] [0 0 1]]")
  with pytest.raises(FileNotFoundError, match="is not one either"):
    registry.get_sequences("south_kensington", tmp_path, "test")


def test_sceneflow_nan_disparity_and_broken_links(tmp_path):
  truth = _sceneflow(tmp_path, np.random.default_rng(1), frames=2)
  gt = tmp_path / "Monkaa/disparity/a_rain_of_stones_x2/left/0006.pfm"
  d = truth["Monkaa/a_rain_of_stones_x2"]["left_d"][0].copy()
  d[2, 3], d[4, 5] = np.nan, np.inf
  frame_io.write_pfm(gt, d)
  frame = registry.get_sequences("monkaa", tmp_path, "train")[0][0]
  assert frame["disparity"][2, 3] == 0 and frame["disparity"][4, 5] == 0  # was NaN / inf
  assert not frame["valid"][2, 3] and not frame["valid"][4, 5] and frame["valid"][3, 3]
  # A sequence behind a link to nothing was left out by the glob that found sequences.
  monkaa = tmp_path / "Monkaa/frames_finalpass"
  for link, target in ((monkaa / "s2", tmp_path / "gone"),
                       (monkaa / "a_rain_of_stones_x2" / "right2", tmp_path / "gone"),
                       (tmp_path / "Driving/frames_finalpass/35mm_focallength", tmp_path / "x")):
    link.symlink_to(target)
    if link.name == "right2":  # not a level where sequences are: no error
      assert len(registry.get_sequences("monkaa", tmp_path, "train")) == 1
    else:
      with pytest.raises(FileNotFoundError, match=f"{link}: a symbolic link to a missing"):
        registry.get_sequences("sceneflow", tmp_path, "train")
    link.unlink()
  # A sequence folder with its right views and GT but no left/ (a half-extracted archive)
  # was left out silently.
  half = monkaa / "eating_x2"
  shutil.copytree(monkaa / "a_rain_of_stones_x2" / "right", half / "right")
  with pytest.raises(FileNotFoundError, match=f"right/ but no left/.*{half}"):
    registry.get_sequences("monkaa", tmp_path, "train")
  shutil.rmtree(half)
  # Frames from SceneFlow's WebP archives: named as such, not "'left' lacks frame '0006'".
  webp = monkaa / "a_rain_of_stones_x2" / "left"
  for png in webp.glob("*.png"):
    png.rename(png.with_suffix(".webp"))
  with pytest.raises(FileNotFoundError, match=f"{webp}: WebP frames"):
    registry.get_sequences("monkaa", tmp_path, "train")
  for frames in webp.glob("*.webp"):
    frames.rename(frames.with_suffix(".png"))
  (tmp_path / "Monkaa/frames_finalpass").rename(tmp_path / "Monkaa/frames_finalpass_webp")
  with pytest.raises(FileNotFoundError, match="frames_finalpass_webp: WebP frames"):
    registry.get_sequences("monkaa", tmp_path, "train")
  (tmp_path / "Monkaa/frames_finalpass_webp").rename(tmp_path / "Monkaa/frames_finalpass")
  left = monkaa / "a_rain_of_stones_x2" / "left"
  left.rename(tmp_path / "moved")
  left.symlink_to(tmp_path / "nowhere")
  with pytest.raises(FileNotFoundError, match=f"{left}: a symbolic link to a missing"):
    registry.get_sequences("monkaa", tmp_path, "train")


def _sintel(root, rng, seqs=(("alley_1", 3), ("cave_2", 2))):
  train, truth = root / "sintel_stereo" / "training", {}
  for name, n in seqs:
    written = {"fx": 1000.0 + len(name)}
    names = [f"frame_{i + 1:04d}" for i in range(n)]
    for dstype in ("clean", "final"):
      _stereo(rng, train / f"{dstype}_left" / name, train / f"{dstype}_right" / name, names,
              written.setdefault(dstype, {}))
    for stem in names:
      rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
      occ = np.where(rng.random((H, W)) < 0.3, 255, 0).astype(np.uint8)
      _png(train / "disparities" / name / f"{stem}.png", rgb)
      _png(train / "occlusions" / name / f"{stem}.png", occ)
      d = rgb[..., 0] * 4.0 + rgb[..., 1] / 64.0 + rgb[..., 2] / 16384.0
      written.setdefault("gt", []).append((d.astype(np.float32), (occ == 0) & (d > 0)))
      k = np.diag([written["fx"], written["fx"], 1.0])
      raw = struct.pack("<f9d12d", 202021.25, *k.ravel(), *np.zeros(12))
      _mkfile(train / "camdata_left" / name / f"{stem}.cam", lambda p, b: p.write_bytes(b), raw)
    truth[name] = written
  return truth


def test_a_frame_missing_from_every_folder_is_warned(tmp_path, caplog):
  rng = np.random.default_rng(4)
  # Sintel's frame numbers, and Infinigen's inside its names (Image_0_0_0003_0.png)
  for make, dataset, folder, frame_3, said in (
      (lambda: _sintel(tmp_path, rng, seqs=(("alley_1", 5),)), "sintel_final",
       "sintel_stereo/training", "frame_0003.*", "Sintel final/alley_1: frame numbers are not "
       "evenly spaced: 1 gap(s), the first after frame_0002.png (next frame_0004.png; usually "
       "+1: a frame missing?)"),
      (lambda: _infinigen(tmp_path, rng, "test", [("scene001", 5)]), "infinigen_sv",
       "InfinigenStereo/test/scene001/frames", "*_0_0_0003_*", "Infinigen test/scene001: frame "
       "numbers are not evenly spaced: 1 gap(s), the first after Image_0_0_0002_0.png (next "
       "Image_0_0_0004_0.png")):
    caplog.clear()
    make()
    with caplog.at_level(logging.WARNING):
      assert len(registry.get_sequences(dataset, tmp_path, "test")[0]) == 5
    assert "not evenly spaced" not in caplog.text
    for path in (tmp_path / folder).rglob(frame_3):
      path.unlink()
    with caplog.at_level(logging.WARNING):
      assert len(registry.get_sequences(dataset, tmp_path, "test")[0]) == 4
    assert said in caplog.text, dataset
    # from the module's own logger, filterable by name (it was the root logger's before)
    assert {r.name for r in caplog.records if "evenly spaced" in r.getMessage()} == {
        "sav_jax.data.base"}
  # Evenly spaced numbers (every 10th frame kept) and names whose last number is no frame
  # number (Infinigen's camera index) are not; Infinigen's own frame number is read.
  caplog.clear()
  base.warn_if_gaps("s", [tmp_path / f"{i:04d}.png" for i in (10, 20, 30, 40)])
  infinigen = [tmp_path / f"Image_0_0_{i:04d}_0.png" for i in (1, 2, 4, 5, 7)]
  base.warn_if_gaps("s", infinigen)
  assert not caplog.text
  with caplog.at_level(logging.WARNING):  # three frames are enough to tell the usual step
    base.warn_if_gaps("s", [tmp_path / f"{i:04d}.png" for i in (1, 2, 4)])
  assert "1 gap(s), the first after 0002.png (next 0004.png; usually +1" in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    base.warn_if_gaps("s", infinigen, registry.infinigen._frame_number)  # pylint: disable=W0212
  assert "2 gap(s), the first after Image_0_0_0002_0.png (next Image_0_0_0004_0.png" in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):  # the usual step is the smallest, not the first
    base.warn_if_gaps("s", [tmp_path / f"{i:04d}.png" for i in (0, 2, 3, 4)])
  assert "1 gap(s), the first after 0000.png (next 0002.png; usually +1" in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):  # a number repeated: not frame numbers, passed
    base.warn_if_gaps("s", [tmp_path / f"{i:04d}.png" for i in (1, 1, 2, 3)])
  assert not caplog.text


def test_a_dataset_one_folder_too_deep_is_named(tmp_path, monkeypatch):
  _sintel(tmp_path / "x", np.random.default_rng(5), seqs=(("alley_1", 2),))
  nested = tmp_path / "sintel_stereo" / "MPI-Sintel-stereo-training-20150305"
  nested.parent.mkdir()
  (tmp_path / "x/sintel_stereo").rename(nested)  # as the archive unpacks into its own folder
  with pytest.raises(FileNotFoundError, match=rf"{nested / 'training'} exists one level deeper: "
                                              rf".* Pass {nested} as its folder"):
    registry.get_sequences("sintel_final", tmp_path, "test")
  assert len(registry.get_sequences("sintel_final", nested, "test")) == 1
  # A folder inside the dataset's (its training/ split folder): that folder is named.
  with pytest.raises(FileNotFoundError, match=rf"{nested / 'training'} is inside the dataset's "
                                              rf"folder {tmp_path / 'sintel_stereo'}: pass"):
    registry.get_sequences("sintel_final", nested / "training", "test")
  assert registry.dataset_folders("sintel_final", tmp_path) == [tmp_path / "sintel_stereo"]
  assert registry.dataset_folders("sintel_final", tmp_path / "sintel_stereo") == [
      tmp_path / "sintel_stereo"]
  assert registry.dataset_folders("kitti_depth", tmp_path) == []
  # Another dataset's training/ one level down is no hint (only the whole missing path is),
  # nor is a folder that cannot be read.
  other = tmp_path / "o"
  (other / "sintel_stereo").mkdir(parents=True)
  (other / "sintel_stereo" / "KITTI2015" / "training").mkdir(parents=True)
  with pytest.raises(FileNotFoundError) as e:
    registry.get_sequences("sintel_final", other, "test")
  assert "one level deeper" not in str(e.value)
  real_is_dir = pathlib.Path.is_dir

  def is_dir(self):
    if "locked" in self.parts:
      raise PermissionError(13, "Permission denied", str(self))
    return real_is_dir(self)

  (other / "sintel_stereo" / "locked").mkdir()
  monkeypatch.setattr(pathlib.Path, "is_dir", is_dir)
  with pytest.raises(FileNotFoundError, match="directory not found"):
    registry.get_sequences("sintel_final", other, "test")


def test_sintel_values_mask_and_scale(tmp_path):
  truth = _sintel(tmp_path, np.random.default_rng(2))
  for dstype in ("clean", "final"):
    seqs = registry.get_sequences(f"sintel_{dstype}", tmp_path, "test")
    assert [s.name for s in seqs] == ["alley_1", "cave_2"]
    for seq in seqs:
      written = truth[seq.name]
      assert seq.sparse and seq.dataset == f"sintel_{dstype}"
      assert seq.depth2disp_scale == pytest.approx(written["fx"] * 0.1)
      _check_images(seq, written[dstype])
      for i in range(len(seq)):
        np.testing.assert_array_equal(seq[i]["disparity"], written["gt"][i][0])
        np.testing.assert_array_equal(seq[i]["valid"], written["gt"][i][1])
  clip = seqs[0].clip(0, 3)
  assert clip["left"].shape == (3, H, W, 3) and clip["valid"].dtype == bool
  rev = seqs[0].clip(2, 3, stride=-1)
  np.testing.assert_array_equal(rev["disparity"], clip["disparity"][::-1])
  with pytest.raises(IndexError):
    seqs[1].clip(1, 2)
  with pytest.raises(TypeError, match="frame index must be an integer, got 1.7"):
    seqs[0][1.7]
  with pytest.raises(ValueError, match="max_frames must be 'official', an integer or None"):
    registry.get_sequences("sintel_final", tmp_path, "test", max_frames="all")
  with pytest.raises(ValueError, match="no official training clips"):
    registry.get_training_clips("sintel_final", tmp_path, frames=2)
  _sintel(tmp_path / "b", np.random.default_rng(3), seqs=(("alley_1", 2),))
  train = tmp_path / "b/sintel_stereo" / "training"
  _png(train / "final_right" / "alley_1" / "frame_0002.png",
       np.zeros((H + 1, W, 3), np.uint8))
  seq = registry.get_sequences("sintel_final", tmp_path / "b/sintel_stereo", "test")[0]
  with pytest.raises(ValueError, match="left .*frame_0002.png.*right"):
    seq[1]
  cam = train / "camdata_left" / "alley_1"
  (cam / "frame_0002.cam").rename(cam / "frame_0003.cam")
  with pytest.raises(ValueError, match="stem mismatch"):
    registry.get_sequences("sintel_clean", tmp_path / "b", "test")
  (cam / "frame_0003.cam").rename(cam / "frame_0002.cam")
  # A focal length of NaN or 0 is refused at once, naming the file (TCC would fail only
  # after the whole prediction, the depth metrics would be NaN).
  good = (cam / "frame_0001.cam").read_bytes()
  for fx in (float("nan"), 0.0):
    raw = struct.pack("<f9d12d", 202021.25, *np.diag([fx, 1.0, 1.0]).ravel(), *np.zeros(12))
    (cam / "frame_0001.cam").write_bytes(raw)
    with pytest.raises(ValueError, match=r"frame_0001\.cam: the focal length fx is (nan|0); it "
                       "must be positive and finite"):
      registry.get_sequences("sintel_clean", tmp_path / "b", "test")
  (cam / "frame_0001.cam").write_bytes(good)
  # A sequence folder that is a dangling link, or a loop of links, is refused: left out,
  # the evaluation would report on the other sequences as if it were the whole set.
  assert len(registry.get_sequences("sintel_clean", tmp_path / "b", "test")) == 1
  for target in (tmp_path / "gone", "cave_2"):  # "cave_2" -> itself: a loop
    link = train / "clean_left" / "cave_2"
    link.symlink_to(target)
    with pytest.raises(FileNotFoundError, match=r"clean_left/cave_2: a symbolic link to a "
                       r"missing file or folder, or a loop of links"):
      registry.get_sequences("sintel_clean", tmp_path / "b", "test")
    link.unlink()


def _dynamic_replica(root, rng, split, seqs, focal=(1.5, 1.5)):
  split_dir, records, truth = root / "dynamic_replica_data" / split, [], {}
  for name, n, fmt in seqs:
    truth[name] = {"fmt": fmt}
    for i in range(n):
      for cam, tx in (("left", 0.3), ("right", 0.3 + 0.05)):
        img, depth = _rgb(rng), rng.uniform(0.5, 5.0, (H, W)).astype(np.float16)
        depth[0, i] = 0.0  # no depth
        _png(split_dir / name / "images" / f"{cam}_{i:06d}.png", img)
        _png(split_dir / name / "depths" / f"{cam}_{i:06d}.geometric.png", depth.view(np.uint16))
        truth[name].setdefault(cam, []).append(img)
        truth[name].setdefault(cam + "_z", []).append(depth.astype(np.float32))
        records.append({
            "sequence_name": name, "camera_name": cam, "frame_number": i,
            "image": {"path": f"{name}/images/{cam}_{i:06d}.png", "size": [H, W]},
            "depth": {"path": f"{name}/depths/{cam}_{i:06d}.geometric.png"},
            "mask": {"path": f"{name}/masks/{cam}_{i:06d}.png"},
            "viewpoint": {"R": np.eye(3).tolist(), "T": [tx, 0.1, 2.0],
                          "focal_length": list(focal), "principal_point": [0.0, 0.0],
                          "intrinsics_format": fmt}})
  with gzip.open(split_dir / f"frame_annotations_{split}.jgz", "wt", encoding="utf8") as f:
    json.dump(records, f)
  return truth


def test_dynamic_replica_depth_scale_and_eval_cut(tmp_path, monkeypatch, caplog):
  seqs_spec = [("seq_b", 3, "ndc_isotropic"), ("seq_a", 2, "ndc_norm_image_bounds")]
  truth = _dynamic_replica(tmp_path, np.random.default_rng(4), "test", seqs_spec)
  # The official cut (150 frames) drops both short sequences, saying so; keep them whole here.
  assert registry.get_sequences("dynamic_replica", tmp_path, "test") == []
  assert "skipped 2 sequence(s) shorter than 150 frames, as the official evaluation does: " \
         "seq_b, seq_a" in caplog.text
  from eval import config as eval_config  # pylint: disable=import-outside-toplevel
  from eval import data as eval_data  # pylint: disable=import-outside-toplevel
  config = eval_config.load_config(
      str(pathlib.Path(__file__).resolve().parents[2] / "configs/eval/dynamic_replica.py"))
  with pytest.raises(ValueError, match=r"all 2 dynamic_replica/test sequences .* shorter than "
                                       r"config.sample_len=150 .* at most 3"):
    eval_data.load_sequences(config, tmp_path)
  config.sample_len = 3  # the skipped sequences are named, for the reports
  kept, skipped = eval_data.load_sequences_and_skipped(config, tmp_path)
  assert [(s.name, len(s)) for s in kept] == [("seq_b", 3)] and skipped == ["seq_a"]
  config.sample_len = 150
  seqs = registry.get_sequences("dynamic_replica", tmp_path, "test", max_frames=None)
  assert [s.name for s in seqs] == ["seq_b", "seq_a"]  # annotation order, not sorted
  for seq in seqs:
    written = truth[seq.name]
    r = min(H, W) / 2 if written["fmt"] == "ndc_isotropic" else W / 2
    assert seq.depth2disp_scale == pytest.approx(1.5 * r * 0.05) and not seq.sparse  # dense
    seq.with_right_disparity = True
    for i in range(len(seq)):
      f = seq[i]
      np.testing.assert_array_equal(f["left"], written["left"][i])
      for key, zkey in (("disparity", "left_z"), ("right_disparity", "right_z")):
        z = written[zkey][i]
        expect = np.where(z > 0, np.float32(seq.depth2disp_scale) / np.where(z > 0, z, 1), 0)
        np.testing.assert_allclose(f[key], expect, rtol=1e-6)
      assert not f["valid"][0, i] and f["valid"].sum() == H * W - 1
  np.testing.assert_array_equal(pickle.loads(pickle.dumps(seqs[0]))[1]["disparity"],
                                seqs[0][1]["disparity"])  # grain workers get pickles
  # Evaluation keeps frames 0..L-1 and, for DR only, drops sequences shorter than L.
  monkeypatch.setitem(registry.EVAL_FRAMES, "dynamic_replica", 3)
  assert [(s.name, len(s)) for s in registry.get_sequences("dynamic_replica", tmp_path,
                                                           "test")] == [("seq_b", 3)]
  monkeypatch.setitem(registry.EVAL_FRAMES, "dynamic_replica", 2)
  cut = registry.get_sequences("dynamic_replica", tmp_path, "test")
  assert [len(s) for s in cut] == [2, 2] and cut[0].files["left"][-1].name == "left_000001.png"
  _dynamic_replica(tmp_path, np.random.default_rng(5), "train", [("s", 2, "ndc_isotropic")])
  (tmp_path / "dynamic_replica_data/train/s/depths/right_000001.geometric.png").unlink()
  with pytest.raises(FileNotFoundError, match="right_000001.geometric.png"):
    registry.get_sequences("dynamic_replica", tmp_path, "train")
  with pytest.raises(FileNotFoundError, match="frame_annotations_valid.jgz"):
    registry.get_sequences("dynamic_replica", tmp_path, "valid")
  _dynamic_replica(tmp_path, np.random.default_rng(5), "train", [("s", 2, "ndc_isotropic")])
  index = tmp_path / "dynamic_replica_data/train/frame_annotations_train.jgz"
  with gzip.open(index, "rt", encoding="utf8") as f:
    records = json.load(f)
  del records[1]["viewpoint"]  # a malformed record names the annotation file and the field
  with gzip.open(index, "wt", encoding="utf8") as f:
    json.dump(records, f)
  with pytest.raises(ValueError, match=r"frame_annotations_train.jgz: malformed .*'viewpoint'"):
    registry.get_sequences("dynamic_replica", tmp_path, "train")
  records[1]["viewpoint"] = dict(records[0]["viewpoint"], T=["abc", 0, 0])  # a string
  with gzip.open(index, "wt", encoding="utf8") as f:
    json.dump(records, f)
  with pytest.raises(ValueError, match=r"frame_annotations_train.jgz: malformed frame record "
                     r"\(TypeError: field viewpoint.T holds 'abc', not a number\)"):
    registry.get_sequences("dynamic_replica", tmp_path, "train")
  # Left and right records are paired by position: an order that pairs different frames
  # is refused (it paired left_000000 with right_000001 silently).
  _dynamic_replica(tmp_path, np.random.default_rng(5), "train", [("s", 2, "ndc_isotropic")])
  with gzip.open(index, "rt", encoding="utf8") as f:
    records = json.load(f)  # l0 r0 l1 r1
  records[1], records[3] = records[3], records[1]
  with gzip.open(index, "wt", encoding="utf8") as f:
    json.dump(records, f)
  with pytest.raises(ValueError, match=r"Dynamic Replica train/s: left and right records "
                     r"number 0 are frames 0 and 1"):
    registry.get_sequences("dynamic_replica", tmp_path, "train")
  # a frame missing from the annotations (frame 2 of 0..4): its neighbours are read as
  # consecutive, which is said
  _dynamic_replica(tmp_path, np.random.default_rng(5), "train", [("s", 5, "ndc_isotropic")])
  with gzip.open(index, "rt", encoding="utf8") as f:
    records = [r for r in json.load(f) if r["frame_number"] != 2]
  with gzip.open(index, "wt", encoding="utf8") as f:
    json.dump(records, f)
  caplog.clear()
  assert len(registry.get_sequences("dynamic_replica", tmp_path, "train")[0]) == 4
  assert "Dynamic Replica train/s: frame numbers are not evenly spaced: 1 gap(s), the first " \
         "after 1 (next 3; usually +1" in caplog.text


def test_a_damaged_dynamic_replica_annotation_file_is_named(tmp_path):
  """A byte changed in the gzip stream (a bad copy) raised zlib.error ("Error -3 while
  decompressing data: invalid distance too far back"), naming no file."""
  _dynamic_replica(tmp_path, np.random.default_rng(5), "test", [("s", 2, "ndc_isotropic")])
  index = tmp_path / "dynamic_replica_data/test/frame_annotations_test.jgz"
  data = index.read_bytes()
  refused = 0
  for i in range(0, len(data), 5):  # (a byte of the header's time stamp or name changes nothing)
    index.write_bytes(data[:i] + bytes([data[i] ^ 0x5A]) + data[i + 1:])
    try:
      registry.get_sequences("dynamic_replica", tmp_path, "test", max_frames=None)
    except ValueError as e:
      assert re.search(r"cannot read Dynamic Replica annotations .*frame_annotations_test\.jgz",
                       str(e)), e
      refused += 1
  assert refused > len(data) // 10


def _infinigen(root, rng, split, scenes, fy=400.0):
  truth = {}
  for scene, n in scenes:
    frames = root / "InfinigenStereo" / split / scene / "frames"
    truth[scene] = {}
    for cam in (0, 1):
      for i in range(n):
        stem = f"0_0_{i + 1:04d}_{cam}"  # Infinigen: cam_rig, resample, frame, subcam
        img, depth = _rgb(rng), rng.uniform(1.0, 50.0, (H, W)).astype(np.float32)
        depth[0, 0], depth[1, 0] = 0.0, np.inf
        _png(frames / "Image" / f"camera_{cam}" / f"Image_{stem}.png", img)
        _mkfile(frames / "Depth" / f"camera_{cam}" / f"Depth_{stem}.npy", np.save, depth)
        pose = np.eye(4)
        pose[:3, 3] = [1.0 + 0.12 * cam, 2.0 + 0.16 * cam, 3.0]  # baseline 0.2 m
        _mkfile(frames / "camview" / f"camera_{cam}" / f"camview_{stem}.npz",
                lambda p, t: np.savez(p, K=np.diag([400.0 + cam, fy, 1.0]), T=t), pose)
        truth[scene].setdefault(cam, []).append((img, depth))
  return truth


@pytest.mark.parametrize("dtype", [bool, np.uint16])
def test_depth_npy_of_another_dtype_is_refused_naming_the_file(tmp_path, dtype):
  """A mask saved as Infinigen's depth read as 1 m everywhere (disparity 80 px, all valid),
  integer depth (millimetres) as tiny disparities: both were taken as ground truth."""
  _infinigen(tmp_path, np.random.default_rng(6), "train", [("scene031", 2)])
  depth = (tmp_path / "InfinigenStereo/train/scene031/frames/Depth/camera_0/"
           "Depth_0_0_0002_0.npy")
  np.save(depth, np.ones((H, W), dtype))
  [seq] = registry.get_sequences("infinigen_sv", tmp_path, "train")
  seq[0]  # pylint: disable=pointless-statement
  with pytest.raises(ValueError, match=rf"{re.escape(str(depth))}: depth of dtype "
                                       rf"{np.dtype(dtype).name}.*expected float depth"):
    seq[1]  # pylint: disable=pointless-statement


def test_infinigen_scale_values_clips_and_eval_cut(tmp_path, monkeypatch):
  truth = _infinigen(tmp_path, np.random.default_rng(6), "train",
                     [("scene031", 12), ("scene032", 4)])
  (tmp_path / "InfinigenStereo/train/scene033.tar.gz").write_bytes(b"")  # not a scene (yet)
  seqs = registry.get_sequences("infinigen_sv", tmp_path / "InfinigenStereo", "train")
  assert [s.name for s in seqs] == ["scene031", "scene032"]
  seq = seqs[1]
  assert not seq.sparse  # dense: the mask is recomputed after augmentation
  assert seq.depth2disp_scale == pytest.approx(400.0 * 0.2)  # K of the left camera
  f = seq[2]
  img, depth = truth["scene032"][0][2]
  np.testing.assert_array_equal(f["left"], img)
  np.testing.assert_allclose(f["disparity"][2:], np.float32(80.0) / depth[2:], rtol=1e-6)
  assert f["disparity"][0, 0] == 0 and f["disparity"][1, 0] == 0  # Z = 0 and Z = inf
  assert not f["valid"][:2, 0].any() and f["valid"][2:].all()
  clips = registry.get_training_clips("infinigen_sv", tmp_path, frames=2, seed=7)
  rng, expect = np.random.default_rng(7), []
  for seq in seqs:  # one stride per start 0, 3, 6, ..., drawn even when the clip is dropped
    for ref in range(0, len(seq), 3):
      k = int(rng.integers(1, 6))
      if ref + 2 * k < len(seq):
        expect.append((seq.name, [ref, ref + k]))
  assert [(c.sequence.name, c.indices) for c in clips] == expect and len(expect) >= 2
  again = registry.get_training_clips("infinigen_sv", tmp_path, frames=2, seed=7)
  assert [c.indices for c in again] == [c.indices for c in clips]
  other = registry.get_training_clips("infinigen_sv", tmp_path, frames=2, seed=8)
  assert [c.indices for c in other] != [c.indices for c in clips]
  one = registry.get_training_clips("infinigen_sv", tmp_path, frames=1)
  assert [c.indices for c in one][:4] == [[0], [3], [6], [9]]
  # Validation during training: consecutive frames, no overlap, only whole clips.
  consecutive = registry.get_consecutive_clips("infinigen_sv", tmp_path, 5, "train")
  assert [(c.sequence.name, c.indices) for c in consecutive] == [
      ("scene031", [0, 1, 2, 3, 4]), ("scene031", [5, 6, 7, 8, 9])]
  assert [c.indices for c in registry.get_consecutive_clips(
      "infinigen_sv", tmp_path, 2, "train")][-2:] == [[0, 1], [2, 3]]  # scene032's
  sample = clips[0].sequence.gather(clips[0].indices)
  assert sample["disparity"].shape == (2, H, W)
  _infinigen(tmp_path, np.random.default_rng(8), "test", [("scene001", 3), ("scene002", 2)])
  _infinigen(tmp_path, np.random.default_rng(8), "val", [("scene217", 1)])  # the script's val/
  assert [s.name for s in registry.get_sequences("infinigen_sv", tmp_path, "val")] == ["scene217"]
  monkeypatch.setitem(registry.EVAL_FRAMES, "infinigen_sv", 3)
  assert [len(s) for s in registry.get_sequences("infinigen_sv", tmp_path, "test")] == [3, 2]
  frames = tmp_path / "InfinigenStereo/test/scene002/frames"
  for kind, ext in (("Depth", "npy"), ("Image", "png"), ("camview", "npz")):
    d = frames / kind / "camera_1"  # first within camera_1, then across the two views
    (d / f"{kind}_0_0_0002_1.{ext}").rename(d / f"{kind}_0_0_0005_1.{ext}")
    with pytest.raises(ValueError, match="stem mismatch") as err:
      registry.get_sequences("infinigen_sv", tmp_path, "test")
    assert ("camera_0" in str(err.value)) == (kind == "camview"), err.value
  for kind, ext in (("Depth", "npy"), ("Image", "png"), ("camview", "npz")):
    d = frames / kind / "camera_1"
    (d / f"{kind}_0_0_0005_1.{ext}").rename(d / f"{kind}_0_0_0002_1.{ext}")
  cam = frames / "camview/camera_1/camview_0_0_0001_1.npz"
  for k, t in ((np.array([400.0, 400.0, 6.0]), np.eye(4)), (np.eye(3), np.zeros(3))):
    np.savez(cam, K=k, T=t)
    with pytest.raises(ValueError, match=f"camview_0_0_0001_1.npz: camview npz has K of shape "
                       rf"\({k.shape[0]},.*T of shape \({t.shape[0]},"):
      registry.get_sequences("infinigen_sv", tmp_path, "test")
  np.savez(cam, K=np.eye(3), pose=np.eye(4))  # T under another name: a KeyError naming nothing
  with pytest.raises(ValueError, match=r"camview_0_0_0001_1.npz: camview npz lacks K or T \(has "
                     r"\['K', 'pose'\]\)"):
    registry.get_sequences("infinigen_sv", tmp_path, "test")


def _vkitti2(root, rng, names, n=2):
  for name in names:
    scene, variation = name.split("_", 1)
    seq = root / "vkitti2" / scene / variation
    for cam in (0, 1):
      for i in range(n):
        img = np.full((H, W, 3), (30 * i + 20, 90 + 60 * cam, 160), np.uint8)
        _png(seq / "frames/rgb" / f"Camera_{cam}" / f"rgb_{i:05d}.jpg", img)
        v = np.array([0, 65535, 100, 50, 200, 1000] * (H * W // 6), np.uint16).reshape(H, W)
        _png(seq / "frames/depth" / f"Camera_{cam}" / f"depth_{i:05d}.png", v)
    rows = ["frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"]
    rows += [f"{i} {c} {725.0087 + i} 725.0087 620.5 187.0" for i in range(n) for c in (0, 1)]
    (seq / "intrinsic.txt").write_text("\n".join(rows) + "\n")


def test_vkitti2_splits_depth_and_sky(tmp_path, caplog):
  _vkitti2(tmp_path, np.random.default_rng(9), registry.vkitti2.TEST)
  test = registry.get_sequences("vkitti2", tmp_path, "test")
  assert [s.name for s in test] == list(registry.vkitti2.TEST)
  s = 725.0087 * 0.532725
  assert test[0].depth2disp_scale == pytest.approx(s)  # first data row only
  assert not test[0].sparse  # dense: the mask is recomputed after augmentation
  f = test[0][1]
  assert np.abs(f["left"].astype(int) - (50, 90, 160)).max() <= 3  # JPEG, Camera_0
  assert np.abs(f["right"].astype(int) - (50, 150, 160)).max() <= 3  # Camera_1
  row = f["disparity"][0, :6]
  np.testing.assert_allclose(row, [0, s / 655.35, s / 1.0, s / 0.5, s / 2.0, s / 10.0],
                             rtol=1e-6)
  np.testing.assert_array_equal(f["valid"][0, :6], [0, 1, 1, 0, 1, 1])  # v=0; d >= 512
  # "train" lists all 50 pairs; missing ones are skipped (the 5 test ones exist here).
  with caplog.at_level(logging.WARNING):
    assert len(registry.get_sequences("vkitti2", tmp_path / "vkitti2", "train")) == 5
  (record,) = [r for r in caplog.records if "VKITTI2" in r.getMessage()]
  warning = record.getMessage()
  assert record.name == "sav_jax.data.vkitti2"
  assert "skipping 45 missing training sequences under" in warning and "Scene01/clone" in warning
  clips = registry.get_training_clips("vkitti2", tmp_path, frames=1)
  assert [c.indices for c in clips] == [[0]] * 5
  # A missing frame file is named (with its key), not only counted; a dangling link too.
  depth = tmp_path / "vkitti2/Scene06/fog/frames/depth/Camera_1"
  (depth / "depth_00001.png").unlink()
  with pytest.raises(ValueError, match=r"VKITTI2 Scene06_fog: frame counts differ: .*; e\.g\. "
                     r"'right_gt' lacks frame 1 \(left has .*Camera_0/rgb_00001\.jpg\)"):
    registry.get_sequences("vkitti2", tmp_path, "test")
  (depth / "depth_00001.png").symlink_to(tmp_path / "gone.png")
  with pytest.raises(FileNotFoundError, match=r"depth_00001\.png: a symbolic link to a missing"):
    registry.get_sequences("vkitti2", tmp_path, "test")
  shutil.rmtree(tmp_path / "vkitti2/Scene06/fog")
  with pytest.raises(FileNotFoundError, match="Scene06/fog"):
    registry.get_sequences("vkitti2", tmp_path, "test")


def test_vkitti2_splits_are_the_official_lists():
  # docs/datasets.md 1.5, written out: train is all 50 pairs of the five scenes and ten
  # variations (the test five included), test the five named ones.
  from sav_jax.data import vkitti2  # pylint: disable=import-outside-toplevel
  assert set(vkitti2.SCENES) == {"Scene01", "Scene02", "Scene06", "Scene18", "Scene20"}
  assert set(vkitti2.VARIATIONS) == {
      "15-deg-left", "15-deg-right", "30-deg-left", "30-deg-right", "clone", "fog", "morning",
      "overcast", "rain", "sunset"}
  assert set(vkitti2.TEST) == {"Scene01_15-deg-left", "Scene02_30-deg-right", "Scene06_fog",
                               "Scene18_morning", "Scene20_rain"}


# P_rect_02[0, 0] of each recording day's calib_cam_to_cam.txt (KITTI raw).
_KITTI_FX = {"2011_09_26": 721.5377, "2011_09_28": 707.0493, "2011_09_29": 718.3351,
             "2011_09_30": 707.0912, "2011_10_03": 718.856}


def _kitti(root, rng, drives, n=2):
  written = {}
  for drive in drives:
    date = drive[:10]
    calib = root / "kitti_depth/input" / date / "calib_cam_to_cam.txt"
    if not calib.exists():
      calib.parent.mkdir(parents=True, exist_ok=True)
      fx = f"{_KITTI_FX[date]:e}"  # fy = fx (rectified)
      calib.write_text("calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.95e-02\n"
                       "T_02: 5.956621e-02 2.900141e-04 2.577209e-03\n"
                       "T_03: -4.731050e-01 5.551470e-03 -5.250882e-03\n"
                       f"P_rect_02: {fx} 0 6.095593e+02 4.485728e+01 0 {fx} "
                       "1.728540e+02 2.163791e-01 0 0 1 2.745884e-03\n")
    for cam in ("image_02", "image_03"):
      for i in range(n):
        name = f"{5 + i:010d}.png"
        img = _rgb(rng)
        _png(root / "kitti_depth/input" / date / drive / cam / "data" / name, img)
        v = np.zeros((H, W), np.uint16)
        v[2, 3], v[4, 5], v[5, 6] = 256 * 20, 300, 70  # 20 m, 1.17 m, 0.27 m (d >= 512)
        v[7, 2 * i + (cam == "image_03")] = 256 * 10  # 10 m: where, tells frame and camera
        _png(root / "kitti_depth/gt_depth" / drive / "proj_depth/groundtruth" / cam / name, v)
        written.setdefault((drive, cam), []).append(img)
  return written


def test_kitti_splits_sparse_depth_and_scale(tmp_path):
  train = ["2011_09_26_drive_0001_sync", "2011_09_26_drive_0009_sync"]
  _kitti(tmp_path, np.random.default_rng(10), kitti_depth.TEST + kitti_depth.VAL + tuple(train),
         n=1)
  test = registry.get_sequences("kitti_depth", tmp_path, "test")
  assert [s.name for s in test] == sorted(kitti_depth.TEST) and len(test) == 13
  assert [s.name for s in registry.get_sequences("kitti_depth", tmp_path, "val")] == [
      "2011_10_03_drive_0042_sync"]
  assert [s.name for s in registry.get_sequences("kitti_depth", tmp_path, "train")] == train
  seq = test[0]
  s = 721.5377 * np.linalg.norm(np.array([5.956621e-02, 2.900141e-04, 2.577209e-03])
                                - [-4.731050e-01, 5.551470e-03, -5.250882e-03])
  assert seq.sparse and seq.depth2disp_scale == pytest.approx(s)
  # each drive takes its own day's calibration (input/<date>/calib_cam_to_cam.txt)
  assert [d.depth2disp_scale for d in test] == pytest.approx(
      [_KITTI_FX[d.name[:10]] * s / 721.5377 for d in test])
  f = seq[0]
  expect = np.zeros((H, W), np.float32)
  expect[2, 3], expect[4, 5], expect[5, 6] = s / 20.0, s / (300 / 256), s / (70 / 256)
  expect[7, 0] = s / 10.0
  np.testing.assert_allclose(f["disparity"], expect, rtol=1e-6)
  assert f["valid"].sum() == 3 and f["valid"][2, 3] and f["valid"][4, 5] and f["valid"][7, 0]
  (tmp_path / "kitti_depth/input/2011_09_26/2011_09_26_drive_0001_sync/image_03/data/"
   "0000000005.png").unlink()
  with pytest.raises(FileNotFoundError, match="image_03/data/0000000005.png"):
    registry.get_sequences("kitti_depth", tmp_path, "train")
  shutil.rmtree(tmp_path / "kitti_depth/gt_depth/2011_09_28_drive_0037_sync")
  with pytest.raises(FileNotFoundError, match="2011_09_28_drive_0037_sync"):
    registry.get_sequences("kitti_depth", tmp_path, "test")
  calib = tmp_path / "kitti_depth/input/2011_09_26/calib_cam_to_cam.txt"
  calib.write_text(calib.read_text().replace("T_03: -4.731050e-01 5.551470e-03 -5.250882e-03",
                                             "T_03: -4.731050e-01 5.551470e-03"))
  with pytest.raises(ValueError, match="calib_cam_to_cam.txt: T_03 has 2 values, not 3"):
    kitti_depth.depth2disp_scale(calib)
  calib.write_text("P_rect_02: 1 2 3\n")
  with pytest.raises(ValueError, match=r"calib_cam_to_cam.txt lacks \['T_02', 'T_03'\]"):
    kitti_depth.depth2disp_scale(calib)


def test_kitti_depth_test_and_val_drives_are_the_codd_lists():
  # docs/datasets.md 1.6, written out: a drive off by one digit moved it between the splits.
  from sav_jax.data.kitti_depth import TEST, VAL  # pylint: disable=import-outside-toplevel
  assert set(TEST) == {f"{d}_sync" for d in (
      "2011_09_26_drive_0002", "2011_09_26_drive_0005", "2011_09_26_drive_0013",
      "2011_09_26_drive_0020", "2011_09_26_drive_0023", "2011_09_26_drive_0036",
      "2011_09_26_drive_0079", "2011_09_26_drive_0095", "2011_09_26_drive_0113",
      "2011_09_28_drive_0037", "2011_09_29_drive_0026", "2011_09_30_drive_0016",
      "2011_10_03_drive_0047")} and len(TEST) == 13
  assert VAL == ("2011_10_03_drive_0042_sync",)


def test_kitti_images_are_the_gt_frames_of_their_camera(tmp_path):
  """image_02 (left) and image_03 (right) frames are found by the GT file name: each frame's
  images and GT are of one frame and one camera; a right GT frame that is not the left's is
  refused (its image of that name exists too: the pair would be two frames)."""
  drive = "2011_09_26_drive_0001_sync"
  written = _kitti(tmp_path, np.random.default_rng(16), (drive,), n=2)
  seq, = registry.get_sequences("kitti_depth", tmp_path, "train")
  seq.with_right_disparity = True
  for i in range(2):
    f = seq[i]
    np.testing.assert_array_equal(f["left"], written[(drive, "image_02")][i])
    np.testing.assert_array_equal(f["right"], written[(drive, "image_03")][i])
    for key, col in (("disparity", 2 * i), ("right_disparity", 2 * i + 1)):
      assert f[key][7, col] == pytest.approx(seq.depth2disp_scale / 10.0)  # 10 m
      assert np.count_nonzero(f[key][7]) == 1
  gt = tmp_path / "kitti_depth/gt_depth" / drive / "proj_depth/groundtruth/image_03"
  (gt / "0000000006.png").rename(gt / "0000000007.png")
  images = tmp_path / "kitti_depth/input/2011_09_26" / drive / "image_03/data"
  shutil.copy(images / "0000000006.png", images / "0000000007.png")
  with pytest.raises(ValueError, match=r"KITTI 2011_09_26_drive_0001_sync: stem mismatch "
                                       r"between .*image_02/0000000006\.png and .*image_03/"
                                       r"0000000007\.png"):
    registry.get_sequences("kitti_depth", tmp_path, "train")


def test_kitti_archive_layout_stray_folders_and_drives_without_images(tmp_path, caplog):
  train = ["2011_09_26_drive_0001_sync", "2011_09_26_drive_0009_sync"]
  _kitti(tmp_path, np.random.default_rng(12), kitti_depth.TEST + kitti_depth.VAL + tuple(train),
         n=1)
  gt = tmp_path / "kitti_depth/gt_depth"
  # As data_depth_annotated.zip unpacks: the drives in train/ and val/, not merged.
  for i, drive in enumerate(sorted(p.name for p in gt.iterdir())):
    (gt / ("train", "val")[i % 2]).mkdir(exist_ok=True)
    (gt / drive).rename(gt / ("train", "val")[i % 2] / drive)
  (gt / "__MACOSX/2011_09_26_drive_0001_sync").mkdir(parents=True)  # a macOS zip's copies
  (gt / "notes").mkdir()
  (gt / "train/tmp").mkdir()  # inside the archive's folders too: not a drive
  with caplog.at_level(logging.WARNING):
    test = registry.get_sequences("kitti_depth", tmp_path, "test")
  assert [s.name for s in test] == sorted(kitti_depth.TEST)
  assert "left out 2 folder(s)" in caplog.text and "notes" in caplog.text
  assert "train/tmp" in caplog.text
  assert "__MACOSX" not in caplog.text
  assert test[0][0]["valid"].sum() == 3
  assert [s.name for s in registry.get_sequences("kitti_depth", tmp_path, "train")] == train
  # A training drive whose raw images were not downloaded is skipped, as officially.
  shutil.rmtree(tmp_path / "kitti_depth/input/2011_09_26/2011_09_26_drive_0009_sync")
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    assert [s.name for s in registry.get_sequences("kitti_depth", tmp_path, "train")] == train[:1]
  assert "skipping 1 training drive(s) without raw images" in caplog.text
  assert "2011_09_26_drive_0009_sync" in caplog.text
  moved = tmp_path / "moved_input"
  shutil.move(tmp_path / "kitti_depth/input/2011_09_26/2011_09_26_drive_0001_sync", moved)
  with caplog.at_level(logging.WARNING), pytest.raises(
      FileNotFoundError, match="no KITTI Depth train drive has its raw images under"):
    registry.get_sequences("kitti_depth", tmp_path, "train")
  shutil.move(moved, tmp_path / "kitti_depth/input/2011_09_26/2011_09_26_drive_0001_sync")
  # ... but a test drive's are required.
  shutil.rmtree(tmp_path / "kitti_depth/input/2011_09_26/2011_09_26_drive_0002_sync")
  with pytest.raises(FileNotFoundError, match="2011_09_26_drive_0002_sync/image_02/data"):
    registry.get_sequences("kitti_depth", tmp_path, "test")
  shutil.copytree(gt / "train" / train[0], gt / train[0])
  with pytest.raises(ValueError, match=f"drive {train[0]} is in .* twice"):
    registry.get_sequences("kitti_depth", tmp_path, "train")


@pytest.mark.parametrize("layout", ["sav", "spring"])
def test_spring_dsp5(tmp_path, layout):
  import h5py  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(11)
  root = tmp_path / "Spring"
  if layout == "sav":
    dirs = (root / "train_frame_left/0001/frame_left", root / "train_frame_right/0001/frame_right",
            root / "train_disp1_left/0001/disp1_left", root / "train_cam_data/0001/cam_data")
  else:
    dirs = tuple(root / "train/0001" / d for d in ("frame_left", "frame_right", "disp1_left",
                                                   "cam_data"))
  full = rng.uniform(1, 50, (2 * H, 2 * W)).astype(np.float32)
  full[0, 0] = full[2, 4] = np.nan
  full[4, 6], full[6, 8] = 0.0, 600.0  # infinitely far, and beyond the dense rule's 512
  full[8, 10], full[10, 12] = np.inf, -np.inf  # not finite: invalid, d = 0 as for NaN
  written = {}
  _stereo(rng, dirs[0], dirs[1], ["frame_left_0001", "frame_left_0002"], written)
  for i in (1, 2):
    (dirs[1] / f"frame_left_{i:04d}.png").rename(dirs[1] / f"frame_right_{i:04d}.png")
    dirs[2].mkdir(parents=True, exist_ok=True)
    with h5py.File(dirs[2] / f"disp1_left_{i:04d}.dsp5", "w") as f:
      f.create_dataset("disparity", data=full if i == 1 else full[::2, ::2])
  dirs[3].mkdir(parents=True)
  # fy differs from fx: the scale takes fx, the first column of the first row.
  (dirs[3] / "intrinsics.txt").write_text("1500.5 1497.25 960 540\n1501 1498 960 540\n")
  for top in {d.parents[1] for d in dirs}:  # a second sequence, a copy of the first
    shutil.copytree(top / "0001", top / "0002")
  seq, second = registry.get_sequences("spring", tmp_path, "test")
  assert (seq.name, second.name) == ("0001", "0002")
  assert seq.depth2disp_scale == pytest.approx(1500.5 * 0.065) and not seq.sparse
  _check_images(seq.head(1), written)  # frame_left/ is the left view, frame_right/ the right
  f = seq[0]
  sub = full[::2, ::2]
  np.testing.assert_array_equal(f["valid"], np.isfinite(sub) & (sub > 0) & (sub < 512))
  np.testing.assert_array_equal(f["disparity"], np.nan_to_num(sub, nan=0.0, posinf=0.0,
                                                             neginf=0.0))
  assert f["disparity"][4, 5] == 0 and f["disparity"][5, 6] == 0
  assert not f["valid"][0, 0] and not f["valid"][1, 2]
  assert not f["valid"][2, 3] and not f["valid"][3, 4] and f["valid"][1, 1]
  with pytest.raises(ValueError, match="disp1_left_0002.dsp5"):  # stored at image size
    seq[1]
  # Strings or records instead of numbers are named with the file, not left to numpy.
  for bad in (np.array([[b"ab"] * W] * H), np.zeros((H, W), [("a", "<f4"), ("b", "<f4")])):
    with h5py.File(dirs[2] / "disp1_left_0002.dsp5", "w") as f:
      f.create_dataset("disparity", data=bad)
    with pytest.raises(ValueError, match=r"disp1_left_0002\.dsp5, array 'disparity': holds .* "
                       "values, not real numbers"):
      seq[1]
  # A byte-order mark (a file saved by a Windows editor) was glued to fx and refused.
  (dirs[3] / "intrinsics.txt").write_bytes(b"\xef\xbb\xbf1400.5 1400.5 960 540\n")
  assert registry.get_sequences("spring", tmp_path, "test")[0].depth2disp_scale == \
      pytest.approx(1400.5 * 0.065)
  (dirs[3] / "intrinsics.txt").write_text("0 0 0 0\n")  # fx = 0: the scale would be 0
  with pytest.raises(ValueError, match=r"intrinsics\.txt: the focal length fx is 0"):
    registry.get_sequences("spring", tmp_path, "test")
  # Both layouts in one folder: one of them was read, the other's sequences left out.
  (root / ("train/0002" if layout == "sav" else "train_frame_left/0002")).mkdir(parents=True)
  with pytest.raises(ValueError, match=r"Spring data under .*Spring in two layouts"):
    registry.get_sequences("spring", tmp_path, "test")
  shutil.rmtree(root / ("train" if layout == "sav" else "train_frame_left"))
  (dirs[2] / "disp1_left_0002.dsp5").rename(dirs[2] / "disp1_left_0003.dsp5")
  with pytest.raises(ValueError, match=r"Spring 0001: stem mismatch between .*frame_left_0002"
                                       r"\.png and .*disp1_left_0003\.dsp5"):
    registry.get_sequences("spring", tmp_path, "test")


def test_south_kensington_images_only(tmp_path, monkeypatch):
  rng = np.random.default_rng(12)
  data = tmp_path / "SouthKensington" / "data"
  written = {}
  names = [f"{i:06d}" for i in range(3)]
  for side in ("left", "right"):
    for n in names:
      img = _rgb(rng)
      _png(data / "indoor_1/images" / side / f"{side}{n}.png", img)
      written.setdefault(side, []).append(img)
  _png(data / "outdoor_1/images/left/left000000.png", _rgb(rng))  # no txt: skipped
  (data / "indoor_1/tracking_data.txt").write_text(
      "Intrinsic: [[910.5 0. 640.]\n [0. 905.25 360.]\n [0. 0. 1.]]\n"  # fx = K[0, 0], not fy
      "Frame 0: Pose: 17\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
  monkeypatch.setitem(registry.EVAL_FRAMES, "south_kensington", 2)
  seqs = registry.get_sequences("south_kensington", tmp_path, "test")
  assert [(s.name, len(s)) for s in seqs] == [("indoor_1", 2)]
  assert seqs[0].depth2disp_scale == pytest.approx(910.5 * 0.12) and not seqs[0].has_gt
  camera = data / "indoor_1/tracking_data.txt"
  text = camera.read_text()
  camera.write_text("Intrinsic: [[9.105e+02 0.000e+00 6.400e+02]\n"  # as numpy may print K
                    " [0.000e+00 9.0525e+02 3.600e+02]\n [0.000e+00 0.000e+00 1.000e+00]]\n")
  assert registry.get_sequences("south_kensington", tmp_path, "test")[0].depth2disp_scale == \
      pytest.approx(910.5 * 0.12)
  camera.write_text("Intrinsic: [[910.5 0. 640. 0.]\n [0. 905.25 360. 0.]\n [0. 0. 1. 0.]\n"
                    " [0. 0. 0. 1.]]\n")  # 4x4: not a K
  with pytest.raises(ValueError, match=rf"no 3x3 `Intrinsic: .*` entry in {camera}"):
    registry.get_sequences("south_kensington", tmp_path, "test")
  camera.write_text(text)
  f = seqs[0][1]
  assert f["disparity"] is None and f["valid"] is None
  np.testing.assert_array_equal(f["right"], written["right"][1])
  clip = seqs[0].clip(0, 2)
  assert clip["left"].shape == (2, H, W, 3) and clip["disparity"] is None
  right = data / "indoor_1/images/right"
  (right / "right000001.png").rename(right / "right000003.png")  # frame 1 is missing
  with pytest.raises(ValueError, match=r"South Kensington indoor_1: stem mismatch between "
                                       r".*left000001\.png and .*right000002\.png"):
    registry.get_sequences("south_kensington", tmp_path, "test")
  (right / "right000003.png").rename(right / "right000001.png")
  # A camera txt behind a dead link left its sequence out silently (as having no txt).
  (data / "outdoor_1/tracking_data.txt").symlink_to(tmp_path / "gone.txt")
  with pytest.raises(FileNotFoundError, match=r"outdoor_1/tracking_data\.txt: a symbolic link "
                     "to a missing file"):
    registry.get_sequences("south_kensington", tmp_path, "test")


def test_registry_names_errors_and_pickling(tmp_path):
  assert set(registry.DATASETS) == {
      "sceneflow", "flyingthings3d", "monkaa", "driving", "sintel_clean", "sintel_final",
      "dynamic_replica", "infinigen_sv", "vkitti2", "kitti_depth", "spring", "south_kensington",
      "tartanair", "folder"}
  with pytest.raises(ValueError, match="unknown dataset 'kitti'.*kitti_depth"):
    registry.get_sequences("kitti", tmp_path, "test")
  with pytest.raises(ValueError, match="frames must be"):
    registry.get_training_clips("vkitti2", tmp_path, frames=0)
  with pytest.raises(FileNotFoundError, match="nowhere"):
    registry.get_sequences("vkitti2", tmp_path / "nowhere", "test")
  _sintel(tmp_path, np.random.default_rng(13), seqs=(("market_2", 2),))
  seq = registry.get_sequences("sintel_final", tmp_path, "test")[0]
  before = {k: v.copy() for k, v in seq[1].items()}
  listing = sorted(p for p in tmp_path.rglob("*"))
  clone = pickle.loads(pickle.dumps(seq))
  for k, v in clone[1].items():
    np.testing.assert_array_equal(v, before[k])
  assert sorted(p for p in tmp_path.rglob("*")) == listing  # nothing written
  assert base.digits_key(tmp_path / "rgb_00012.jpg") == base.digits_key(tmp_path / "d_12.png")
  with pytest.raises(ValueError, match="head"):
    seq.head(3)


def test_gather_names_the_frame_of_another_size(tmp_path):
  rng = np.random.default_rng(14)
  files = {"left": [], "right": []}
  for i in range(4):
    size = (H - 2, W) if i == 3 else (H, W)  # as a Sintel frame 3 at 66x128 among 68x128
    for side in files:
      img = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
      _png(tmp_path / side / f"frame_{i:04d}.png", img)
      files[side].append(tmp_path / side / f"frame_{i:04d}.png")
  seq = base.StereoSequence("market_2", files, dataset="sintel_final")
  assert seq.clip(0, 3)["left"].shape == (3, H, W, 3)
  for one in (str(files["left"][0]), files["left"][0]):  # a str made one frame per letter
    with pytest.raises(ValueError, match=r"sintel_final/market_2: files\['left'\] must be a "
                                         r"list of paths, one per frame, got the single path"):
      base.StereoSequence("market_2", {**files, "left": one}, dataset="sintel_final")
  odd = tmp_path / "left" / "frame_0003.png"
  with pytest.raises(ValueError, match=rf"sintel_final/market_2: frame 3 {odd} is {H - 2}x{W} "
                                       rf"but frame 1 .*frame_0001.png is {H}x{W}"):
    seq.gather([1, 2, -1])


def test_a_sequence_refuses_unpaired_file_lists_and_a_scale_that_is_not_positive():
  """Every reader's sequence (and a reader of one's own) is built by StereoSequence: a missing
  right list, lists of different lengths (frame i paired with another frame's file) and a
  depth2disp scale of 0, below 0 or not finite (disparities of 0, negative or NaN) are refused."""
  pair = {"left": ["l0.png", "l1.png"], "right": ["r0.png", "r1.png"]}
  assert len(base.StereoSequence("s", pair, depth2disp_scale=80.0)) == 2
  for files, message in (({"left": pair["left"]}, "images/s: no 'right' image list"),
                         ({**pair, "right": ["r0.png"]}, "counts differ or are zero: "
                                                         "{'left': 2, 'right': 1}"),
                         ({**pair, "left_gt": ["d1.png"]}, "counts differ")):
    with pytest.raises(ValueError, match=re.escape(message)):
      base.StereoSequence("s", files)
  for scale in (0.0, -80.0, np.nan, np.inf):
    with pytest.raises(ValueError, match="images/s: depth2disp scale must be positive and "
                                         "finite"):
      base.StereoSequence("s", pair, depth2disp_scale=scale)
  with pytest.raises(ValueError, match="d/s: depth2disp scale must be positive and finite, "
                                       "got None"):  # depth without one has no disparity
    base.DepthSequence("s", pair, dataset="d", depth2disp_scale=None, depth_reader=np.load)


class _WeightedGT(base.StereoSequence):
  """A reader of your own whose valid mask is weights (e.g. a mask resized bilinearly)."""

  def _read_gt(self, i, side):
    return (np.full((H, W), 3.0, np.float32),
            np.tile(np.float32([0.0, 0.3, 0.5, 0.6, 1.0, 2.0]), (H, W // 6)))


def test_a_readers_valid_weights_count_above_one_half_as_in_the_metrics(tmp_path):
  img = tmp_path / "frame.png"
  _png(img, np.zeros((H, W, 3), np.uint8))
  seq = _WeightedGT("s", {"left": [img], "right": [img], "left_gt": [img]}, dataset="mine")
  valid = seq[0]["valid"]  # a cast to bool counted every weight above 0 (0.3 too)
  assert valid.dtype == bool
  assert valid.shape == (H, W)
  np.testing.assert_array_equal(valid[0, :6], [False, False, False, True, True, True])
  np.testing.assert_array_equal(seq.clip(0, 1)["valid"][0], valid)


class _OwnReader(base.StereoSequence):
  """A reader of your own that returns what `kind` says (its mistakes, or a list)."""

  kind = "pair"

  def _read_gt(self, i, side):
    d = np.full((H, W), 3.0, np.float32)
    return {"bare": lambda: d, "list": lambda: (d.tolist(), np.ones((H, W), bool)),
            "mask": lambda: (d, np.ones((3, 3), bool)),
            "width": lambda: (d[:, 1:], np.ones((H, W), bool)),
            "bools": lambda: (d > 0, np.ones((H, W), bool)),
            "strings": lambda: (d.astype(str), np.ones((H, W), bool))}[self.kind]()


@pytest.mark.parametrize("kind,message", [
    ("bare", r"_OwnReader._read_gt returned an array of shape \(\d+, \d+\) float32 for "
             r".*gt.npy; expected a pair \(disparity \[H, W\], valid \[H, W\]\)"),
    ("mask", r"_OwnReader._read_gt: the valid mask of .*gt.npy is \(3, 3\) bool; expected "
             r"\(\d+, \d+\) bool \(or weights\) as the image .*frame.png"),
    ("width", rf"ground truth .*gt.npy is \({H}, {W - 1}\) but the image .*frame.png is "
              rf"\({H}, {W}\)"),
    ("strings", r"_OwnReader._read_gt: the disparity of .*gt.npy is of dtype <U\d+; expected "
                r"numbers"),
    ("bools", r"_OwnReader._read_gt: the disparity of .*gt.npy is of dtype bool; expected "
              r"numbers")])  # (a mask as the disparity: 1 px wherever it is set)
def test_what_a_readers_read_gt_returns_is_checked_naming_the_reader_and_file(tmp_path, kind,
                                                                              message):
  # A bare array failed as "too many values to unpack", a mask of another size was carried
  # into training (dense clips recompute theirs) or the metrics: neither named the file.
  img = tmp_path / "frame.png"
  _png(img, np.zeros((H, W, 3), np.uint8))
  seq = _OwnReader("s", {"left": [img], "right": [img], "left_gt": [tmp_path / "gt.npy"]},
                   dataset="mine")
  seq.kind = kind
  with pytest.raises(ValueError, match=message):
    seq.clip(0, 1)
  seq.kind = "list"  # numbers in a list are numbers
  np.testing.assert_array_equal(seq.clip(0, 1)["disparity"], np.full((1, H, W), 3.0))


def test_hidden_files_are_skipped_and_frame_numbers_sort_as_numbers(tmp_path):
  # macOS archives leave `._<name>` copies beside every file, notebooks `.ipynb_checkpoints`:
  # shell globs (and the official loaders) skip them, so must we.
  rng = np.random.default_rng(13)
  _sceneflow(tmp_path, rng, frames=2)
  seq_dir = tmp_path / "Monkaa/frames_finalpass/a_rain_of_stones_x2"
  for junk in (seq_dir / "left/._0006.png", seq_dir / "right/._0006.png",
               tmp_path / "Monkaa/disparity/a_rain_of_stones_x2/left/._0006.pfm"):
    junk.write_bytes(b"\x00\x05\x16\x07 AppleDouble")
  (tmp_path / "Monkaa/frames_finalpass/.ipynb_checkpoints/left").mkdir(parents=True)
  (tmp_path / "Monkaa/frames_finalpass/__MACOSX/left").mkdir(parents=True)  # a macOS zip's
  seqs = registry.get_sequences("monkaa", tmp_path, "train")
  assert [(s.name, len(s)) for s in seqs] == [("Monkaa/a_rain_of_stones_x2", 2)]
  assert seqs[0][0]["left"].shape == (H, W, 3)
  # Unpadded frame numbers (South Kensington's naming is not documented) in time order,
  # and a hidden copy of the camera file is not read as the camera file.
  data = tmp_path / "SouthKensington" / "data"
  written = []
  for i in (0, 1, 2, 9, 10, 11):
    img = _rgb(rng)
    written.append(img)
    for side in ("left", "right"):
      _png(data / "s1/images" / side / f"{side}{i}.png", img)
  (data / "s1/._tracking_data.txt").write_bytes(b"\x00\x05\x16\x07\xff\xfe")
  (data / "s1/README.txt").write_text("Recorded in South Kensington.\n")  # not the camera file
  (data / "s1/tracking_data.txt").write_text("Intrinsic: [[500. 0. 10.]\n [0. 500. 8.]\n"
                                             " [0. 0. 1.]]\n")
  (data / ".ipynb_checkpoints").mkdir()
  seq, = registry.get_sequences("south_kensington", tmp_path, "test")
  assert [p.name for p in seq.files["left"]] == [f"left{i}.png" for i in (0, 1, 2, 9, 10, 11)]
  assert seq.depth2disp_scale == pytest.approx(500 * 0.12)
  np.testing.assert_array_equal(seq.clip(0, 6)["left"], np.stack(written))
  assert base.list_dirs(data) == [data / "s1"]
  (data / "s1/tracking_data.txt").rename(data / "s1/camera.txt")  # after README.txt by name
  seq, = registry.get_sequences("south_kensington", tmp_path, "test")
  assert seq.depth2disp_scale == pytest.approx(500 * 0.12)
  (data / "s1/zed.txt").write_text("Intrinsic: [[700. 0. 10.]\n [0. 700. 8.]\n [0. 0. 1.]]\n")
  seq, = registry.get_sequences("south_kensington", tmp_path, "test")  # the first by name
  assert seq.depth2disp_scale == pytest.approx(500 * 0.12)
  (data / "s1/zed.txt").unlink()
  (data / "s1/README.txt").write_bytes("Enregistré à South Kensington\n".encode("latin-1"))
  seq, = registry.get_sequences("south_kensington", tmp_path, "test")  # not UTF-8: passed over
  assert seq.depth2disp_scale == pytest.approx(500 * 0.12)
  (data / "s1/README.txt").write_text("Recorded in South Kensington.\n")
  (data / "s1/camera.txt").unlink()
  with pytest.raises(ValueError, match=r"no `Intrinsic: .* entry in any .txt of .*s1 \(read: "
                                       r"README.txt\)"):
    registry.get_sequences("south_kensington", tmp_path, "test")


def test_natural_order_of_frame_names():
  names = ["f10.png", "f2.png", "f1.png", "0010.png", "0009.png", "1701.5.png", "1701.25.png",
           "1701.125.png", "1403636579.763555584.png", "1403636579.063555584.png"]
  assert sorted(names, key=base.natural_key) == [
      "0009.png", "0010.png", "1701.125.png", "1701.25.png", "1701.5.png",  # decimal timestamps
      "1403636579.063555584.png", "1403636579.763555584.png", "f1.png", "f2.png", "f10.png"]
  padded = [f"frame_{i:04d}_left.png" for i in (3, 12, 0, 100)]
  assert sorted(padded, key=base.natural_key) == sorted(padded)  # the official sorted() order


def test_camera_data_errors_name_the_file(tmp_path):
  """A focal length or baseline that is 0, negative or NaN, a camera file that is not UTF-8
  text and a depth array that is not [H, W] are named by their file (they named only the
  sequence, or nothing: a UnicodeDecodeError, numpy's item assignment of a 0-d array)."""
  rng = np.random.default_rng(11)
  _vkitti2(tmp_path, rng, registry.vkitti2.TEST, n=1)
  intrinsic = tmp_path / "vkitti2/Scene01/15-deg-left/intrinsic.txt"
  good = intrinsic.read_bytes()
  intrinsic.write_text("frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n0 0 0 725 620 187\n")
  with pytest.raises(ValueError, match=f"{intrinsic}: the focal length fx is 0"):
    registry.get_sequences("vkitti2", tmp_path, "test")
  intrinsic.write_text("frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n\n0 0 730 725 620 187\n")
  assert registry.get_sequences("vkitti2", tmp_path, "test")[0].depth2disp_scale == \
      pytest.approx(730 * 0.532725)  # a blank line is no row
  intrinsic.write_text("frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n")  # the header only
  with pytest.raises(ValueError, match=f"malformed VKITTI2 intrinsics .*: {intrinsic}"):
    registry.get_sequences("vkitti2", tmp_path, "test")
  intrinsic.write_bytes(good.decode().encode("utf-16"))
  with pytest.raises(ValueError, match=f"VKITTI2 intrinsics {intrinsic} is not UTF-8 text"):
    registry.get_sequences("vkitti2", tmp_path, "test")

  drives = kitti_depth.TEST
  _kitti(tmp_path, rng, drives, n=1)
  calib = tmp_path / "kitti_depth/input" / drives[0][:10] / "calib_cam_to_cam.txt"
  good = calib.read_text()
  calib.write_text(good.replace("P_rect_02: 7.215377e+02", "P_rect_02: nan"))
  with pytest.raises(ValueError, match=f"{calib}: the focal length fx is nan"):
    registry.get_sequences("kitti_depth", tmp_path, "test")
  calib.write_text(good.replace("T_03: -4.731050e-01 5.551470e-03 -5.250882e-03",
                                "T_03: 5.956621e-02 2.900141e-04 2.577209e-03"))
  with pytest.raises(ValueError, match=f"{calib}: the stereo baseline is 0"):
    registry.get_sequences("kitti_depth", tmp_path, "test")
  calib.write_bytes(b"\xff\xfe" + good.encode())
  with pytest.raises(ValueError, match=f"KITTI calibration {calib} is not UTF-8 text"):
    registry.get_sequences("kitti_depth", tmp_path, "test")

  _infinigen(tmp_path, rng, "test", [("scene040", 2)])
  frames = tmp_path / "InfinigenStereo/test/scene040/frames"
  np.save(frames / "Depth/camera_0/Depth_0_0_0001_0.npy", np.array(5.0, np.float32))
  seq = registry.get_sequences("infinigen_sv", tmp_path / "InfinigenStereo", "test")[0]
  with pytest.raises(ValueError, match=r"Depth_0_0_0001_0\.npy has shape \(\); expected \[H, W\]"):
    seq[0]
  right = frames / "camview/camera_1/camview_0_0_0001_1.npz"
  left = frames / "camview/camera_0/camview_0_0_0001_0.npz"
  with np.load(left) as z:
    np.savez(right, K=z["K"], T=z["T"])  # the right camera where the left one is
  with pytest.raises(ValueError, match=f"{left} and {right}: the stereo baseline is 0"):
    registry.get_sequences("infinigen_sv", tmp_path / "InfinigenStereo", "test")

  sk = tmp_path / "SouthKensington/data/indoor_1"
  _png(sk / "images/left/left000000.png", _rgb(rng))
  _png(sk / "images/right/right000000.png", _rgb(rng))
  (sk / "tracking_data.txt").write_bytes("Intrinsic: [[910.5 0. 640.]\n".encode("utf-16"))
  with pytest.raises(ValueError, match="South Kensington camera file .*tracking_data.txt is not "
                     "UTF-8 text"):
    registry.get_sequences("south_kensington", tmp_path, "test")


def test_dynamic_replica_camera_errors_name_the_annotation(tmp_path, monkeypatch):
  monkeypatch.setitem(registry.EVAL_FRAMES, "dynamic_replica", 2)
  _dynamic_replica(tmp_path, np.random.default_rng(12), "test", [("s", 2, "ndc_isotropic")])
  index = tmp_path / "dynamic_replica_data/test/frame_annotations_test.jgz"
  with gzip.open(index, "rt", encoding="utf8") as f:
    records = json.load(f)

  def load(edit):
    changed = json.loads(json.dumps(records))
    edit(changed)
    with gzip.open(index, "wt", encoding="utf8") as f:
      json.dump(changed, f)
    return registry.get_sequences("dynamic_replica", tmp_path, "test")

  lefts = lambda recs: [r for r in recs if r["camera_name"] == "left"]  # noqa: E731
  swap = lambda recs: [r.update(camera_name={"left": "right", "right": "left"}[r["camera_name"]])
                       for r in recs]  # noqa: E731
  with pytest.raises(ValueError, match=rf"{index} \(Dynamic Replica test/s, frame 0\): the stereo "
                     r"baseline is -[\d.]+; it must be positive"):
    load(swap)  # a reversed rig gave negative disparities named by the sequence only
  with pytest.raises(ValueError, match=rf"{index} \(Dynamic Replica test/s, frame 0\): unknown Dynamic "
                     "Replica intrinsics format 'pixels'"):
    load(lambda recs: lefts(recs)[0]["viewpoint"].update(intrinsics_format="pixels"))
  with pytest.raises(ValueError, match=rf"{index} \(Dynamic Replica test/s, frame 0\): the focal length "
                     "fx is 0"):
    load(lambda recs: lefts(recs)[0]["viewpoint"].update(focal_length=[0.0, 0.0]))
  # A 400-digit focal length (OverflowError) and a NaN image size ("cannot convert float NaN
  # to integer"): tracebacks naming no file.
  with pytest.raises(ValueError, match=rf"{index}: malformed frame record \(TypeError: field "
                     r"viewpoint.focal_length holds 1(0){39}, not a finite number\)"):
    load(lambda recs: lefts(recs)[0]["viewpoint"].update(focal_length=[10**400, 1.0]))
  with pytest.raises(ValueError, match=rf"{index}: malformed frame record \(TypeError: field "
                     r"image.size holds nan, not a finite number\)"):
    load(lambda recs: lefts(recs)[0]["image"].update(size=[float("nan"), W]))
  # Images resized under the original annotation: the scale would be off by the factor.
  seq = load(lambda recs: [r["image"].update(size=[2 * H, 2 * W]) for r in recs])[0]
  with pytest.raises(ValueError, match=rf"is {H}x{W} but {index} gives image.size "
                     rf"{2 * H}x{2 * W} for dynamic_replica/s"):
    seq[0]
  assert load(lambda recs: None)[0][1]["disparity"].shape == (H, W)


def test_training_clips_take_their_first_frames_camera(tmp_path):
  """The official loader converts a clip's depth with the camera of the clip's first frame;
  evaluation (whole sequences, `seq[i]`, `clip(0, n)`) with frame 0's."""
  _dynamic_replica(tmp_path, np.random.default_rng(13), "train", [("s", 4, "ndc_isotropic")])
  index = tmp_path / "dynamic_replica_data/train/frame_annotations_train.jgz"
  with gzip.open(index, "rt", encoding="utf8") as f:
    records = json.load(f)
  for r in records:  # frames 2 and 3 are taken with twice the focal length
    if r["frame_number"] >= 2:
      r["viewpoint"]["focal_length"] = [3.0, 3.0]
  with gzip.open(index, "wt", encoding="utf8") as f:
    json.dump(records, f)
  seq, = registry.get_sequences("dynamic_replica", tmp_path, "train")
  s0 = 1.5 * min(H, W) / 2 * 0.05
  assert seq.depth2disp_scale == pytest.approx(s0)
  assert seq.clip_scale(2) == pytest.approx(2 * s0) and seq.clip_scale(1) == pytest.approx(s0)
  whole = seq.clip(0, 4)["disparity"]
  np.testing.assert_array_equal(whole[2], seq[2]["disparity"])  # the sequence: frame 0's
  for indices, factor in (([2, 3], 2.0), ([1, 2], 1.0), ([3, 1], 2.0)):
    got = pickle.loads(pickle.dumps(seq)).gather(indices)["disparity"]
    np.testing.assert_allclose(got, whole[indices] * factor, rtol=1e-6)
  assert seq.depth2disp_scale == pytest.approx(s0)  # gather left the sequence as it was

  _infinigen(tmp_path, np.random.default_rng(14), "train", [("scene031", 3)])
  cams = tmp_path / "InfinigenStereo/train/scene031/frames/camview/camera_1"
  pose = np.eye(4)
  pose[:3, 3] = [1.0 + 0.24, 2.0 + 0.32, 3.0]  # frame 2's baseline doubled: 0.4 m
  np.savez(cams / "camview_0_0_0003_1.npz", K=np.diag([401.0, 400.0, 1.0]), T=pose)
  seq, = registry.get_sequences("infinigen_sv", tmp_path, "train")
  assert seq.depth2disp_scale == pytest.approx(80.0) and seq.clip_scale(2) == pytest.approx(160.0)
  whole = seq.clip(0, 3)["disparity"]
  np.testing.assert_allclose(seq.gather([2, 1])["disparity"], whole[[2, 1]] * 2, rtol=1e-6)
  np.testing.assert_array_equal(seq.gather([1, 2])["disparity"], whole[[1, 2]])
  pose[:3, 3] = [1.0 + 0.18, 2.0 + 0.24, 3.0]  # frame 1's baseline 0.3 m: a clip from frame 1
  np.savez(cams / "camview_0_0_0002_1.npz", K=np.diag([401.0, 400.0, 1.0]), T=pose)
  seq, = registry.get_sequences("infinigen_sv", tmp_path, "train")
  assert seq.clip_scale(1) == pytest.approx(120.0) and seq.clip_scale(0) == pytest.approx(80.0)


def test_depth2disp_scale_takes_the_horizontal_focal_length(tmp_path):
  """The scale is fx[px] * baseline (DR: focal_length[0]; Infinigen: K[0, 0]); fixtures with
  fx == fy could not tell fx from fy. In DR's ndc_norm_image_bounds format a camera with square
  pixels on a non-square image has fx_ndc != fy_ndc (fx_ndc = f / (W/2), fy_ndc = f / (H/2))."""
  f_px = 9.0  # square pixels: 1.5 * W/2 = 2.25 * H/2 in NDC
  _dynamic_replica(tmp_path, np.random.default_rng(15), "train",
                   [("bounds", 2, "ndc_norm_image_bounds"), ("iso", 2, "ndc_isotropic")],
                   focal=(f_px / (W / 2), f_px / (H / 2)))
  bounds, iso = registry.get_sequences("dynamic_replica", tmp_path, "train")
  assert bounds.depth2disp_scale == pytest.approx(f_px * 0.05)  # fy_ndc gave 13.5 px
  assert bounds.clip_scale(1) == pytest.approx(f_px * 0.05)
  assert iso.depth2disp_scale == pytest.approx(1.5 * min(H, W) / 2 * 0.05)  # fx_ndc * H/2
  z = bounds.depth_reader(bounds.files["left_gt"][1])  # (row 0 holds a pixel without depth)
  np.testing.assert_allclose(bounds[1]["disparity"][1:], np.float32(f_px * 0.05) / z[1:],
                             rtol=1e-6)
  # Infinigen: K = diag(400, 300, 1), baseline 0.2 m
  _infinigen(tmp_path, np.random.default_rng(16), "train", [("scene031", 2)], fy=300.0)
  seq, = registry.get_sequences("infinigen_sv", tmp_path, "train")
  assert seq.depth2disp_scale == pytest.approx(400.0 * 0.2)  # K[1, 1] gave 60
  assert seq.clip_scale(1) == pytest.approx(400.0 * 0.2)  # a clip's own camera: K[0, 0] too


def test_infinigen_baseline_is_the_distance_between_the_camera_centres(tmp_path):
  """`K_left[0, 0] * ||t_left - t_right||` over all three axes (a rig in Blender world
  coordinates need not be level or face along an axis), of a 4x4 or a 3x4 pose."""
  from sav_jax.data import infinigen  # pylint: disable=import-outside-toplevel
  for name, rows, shift in (("left", 4, (0.0, 0.0, 0.0)), ("right", 3, (0.12, -0.09, 0.08))):
    pose = np.eye(4)[:rows]
    pose[:, 3] = np.array([1.0, 2.0, 3.0, 1.0][:rows]) + np.array([*shift, 0.0][:rows])
    np.savez(tmp_path / f"{name}.npz", K=np.diag([400.0, 300.0, 1.0]), T=pose)
  # sqrt(0.12^2 + 0.09^2 + 0.08^2) = 0.17 m (0.15 m in x and y only, 0.12 m in x)
  assert infinigen.depth2disp_scale(tmp_path / "left.npz", tmp_path / "right.npz") == \
      pytest.approx(400.0 * 0.17)


def test_official_evaluation_lengths_are_the_documented_ones():
  """`EVAL_FRAMES` (frames 0..L-1 of each test sequence) as docs/datasets.md gives the
  official `sample_len`: DR and Infinigen 150, VKITTI2, KITTI and South Kensington 300; Sintel
  evaluates every frame, and the others (no official protocol) are left whole."""
  builtin = ("sceneflow", "flyingthings3d", "monkaa", "driving", "sintel_clean", "sintel_final",
             "dynamic_replica", "infinigen_sv", "vkitti2", "kitti_depth", "spring",
             "south_kensington", "tartanair", "folder")
  assert {name: registry.EVAL_FRAMES[name] for name in builtin
          if name in registry.EVAL_FRAMES} == {
              "dynamic_replica": 150, "infinigen_sv": 150, "vkitti2": 300, "kitti_depth": 300,
              "south_kensington": 300}


class _FixedStride:
  """A stand-in for the generator of `strided_clips`: every stride draw gives `k`."""

  def __init__(self, k):
    self.k, self.calls = k, []

  def integers(self, low, high):
    self.calls.append((low, high))
    return self.k


def test_strided_clips_keep_a_clip_only_when_start_plus_k_times_t_is_below_n():
  """The official rule keeps a clip when start + k*T < N (strictly), although start + (T-1)k
  < N would fit: N = 8, T = 5, k = 1 keeps [0..4] and drops [3..7]."""
  rng = _FixedStride(1)
  assert base.strided_clips(8, 5, rng) == [[0, 1, 2, 3, 4]]
  assert rng.calls == [(1, 6)] * 3  # a stride in 1..5 per start 0, 3, 6, dropped clips too
  assert base.strided_clips(9, 5, _FixedStride(1)) == [[0, 1, 2, 3, 4], [3, 4, 5, 6, 7]]
  assert base.strided_clips(12, 3, _FixedStride(2)) == [[0, 2, 4], [3, 5, 7]]  # not [6, 8, 10]
  rng = _FixedStride(4)
  assert base.strided_clips(7, 1, rng) == [[0], [3]] and rng.calls == []  # T = 1: k = 1


def test_clip_with_a_negative_start_is_out_of_range_not_wrapped(tmp_path):
  """`seq[-1]` is the last frame, but a clip reaching before frame 0 is an error: wrapped, it
  would splice the last frame in front of the first ones silently."""
  files = {"left": [], "right": []}
  for i in range(4):
    for side in files:
      _png(tmp_path / side / f"{i:04d}.png", np.full((H, W, 3), 10 * i, np.uint8))
      files[side].append(tmp_path / side / f"{i:04d}.png")
  seq = base.StereoSequence("s", files)
  assert seq[-1]["left"][0, 0, 0] == 30
  for start, length, stride in ((-1, 3, 1), (1, 3, -1), (2, 3, 1)):
    with pytest.raises(IndexError, match=r"clip -?\d\.\.-?\d out of range for images/s "
                                         r"\(4 frames\)"):
      seq.clip(start, length, stride)
  assert list(seq.clip(3, 4, stride=-1)["left"][:, 0, 0, 0]) == [30, 20, 10, 0]
  with pytest.raises(ValueError, match="clip needs length >= 1 and stride != 0, got 3, 0"):
    seq.clip(1, 3, stride=0)  # (frame 1 three times, a still video)


def _tartanair(root, rng, entries, n=3):
  truth = {}
  for scene, difficulty, part in entries:
    seq = root / "TartanAir" / scene / difficulty / part
    for i in range(n):
      left, right = _rgb(rng), _rgb(rng)
      depth = rng.uniform(0.5, 200.0, (H, W)).astype(np.float32)
      depth[0, 0] = 0.0  # no depth
      _png(seq / "image_left" / f"{i:06d}_left.png", left)
      _png(seq / "image_right" / f"{i:06d}_right.png", right)
      _mkfile(seq / "depth_left" / f"{i:06d}_left_depth.npy", np.save, depth)
      truth.setdefault("_".join((scene, difficulty, part)), []).append((left, right, depth))
    (seq / "pose_left.txt").write_text("0 0 0 0 0 0 1\n" * n)
  return truth


def test_tartanair_splits_depth_and_clips(tmp_path, caplog):
  entries = [("amusement", "Easy", "P000"), ("abandonedfactory", "Hard", "P002"),
             ("abandonedfactory", "Easy", "P002"), ("abandonedfactory", "Easy", "P001"),
             ("abandonedfactory", "Hard", "P000"), ("abandonedfactory", "Easy", "P000")]
  truth = _tartanair(tmp_path, np.random.default_rng(15), entries, n=7)
  test = registry.get_sequences("tartanair", tmp_path, "test")
  # the official order: scenes by name, Easy before Hard, parts by name
  assert [s.name for s in test] == ["abandonedfactory_Easy_P002", "abandonedfactory_Hard_P002"]
  assert "15 of the 17 test sequences are missing" in caplog.text and "amusement/Easy/P007" \
      in caplog.text
  train = registry.get_sequences("tartanair", tmp_path / "TartanAir", "train")
  assert [s.name for s in train] == ["abandonedfactory_Easy_P000", "abandonedfactory_Easy_P001",
                                     "abandonedfactory_Hard_P000", "amusement_Easy_P000"]
  seq = test[0]
  assert seq.depth2disp_scale == pytest.approx(80.0) and not seq.has_right_disparity
  assert not seq.sparse  # dense
  for i in (0, 6):
    f = pickle.loads(pickle.dumps(seq))[i]
    left, right, depth = truth[seq.name][i]
    np.testing.assert_array_equal(f["left"], left)
    np.testing.assert_array_equal(f["right"], right)
    np.testing.assert_allclose(f["disparity"].ravel()[1:], 80.0 / depth.ravel()[1:], rtol=1e-6)
    assert f["disparity"][0, 0] == 0 and not f["valid"][0, 0] and f["valid"].sum() == H * W - 1
  clips = registry.get_training_clips("tartanair", tmp_path, frames=2, seed=3)
  rng, expect = np.random.default_rng(3), []
  for s in train:  # the official strided clips, as for Dynamic Replica and the others
    for ref in range(0, len(s), 3):
      k = int(rng.integers(1, 6))
      if ref + 2 * k < len(s):
        expect.append((s.name, [ref, ref + k]))
  assert [(c.sequence.name, c.indices) for c in clips] == expect and expect
  # A frame missing from one folder is named; so is a split without sequences.
  (tmp_path / "TartanAir/amusement/Easy/P000/depth_left/000003_left_depth.npy").unlink()
  with pytest.raises(ValueError, match=r"TartanAir amusement_Easy_P000: frame counts differ.*"
                                       r"'left_gt' lacks frame 3"):
    registry.get_sequences("tartanair", tmp_path, "train")
  shutil.rmtree(tmp_path / "TartanAir/abandonedfactory")
  with pytest.raises(FileNotFoundError, match="no TartanAir test sequences under"):
    registry.get_sequences("tartanair", tmp_path, "test")
  with pytest.raises(ValueError, match="tartanair has no split 'val'"):
    registry.get_sequences("tartanair", tmp_path, "val")


def test_tartanair_only_sequences_of_the_other_split_are_named_not_a_bad_layout(tmp_path):
  """A partial download in the right layout whose parts are all of the other split: the error
  names them and the split rule (it said the layout was not the expected one)."""
  _tartanair(tmp_path, np.random.default_rng(0), [("abandonedfactory", "Easy", "P000")], n=2)
  with pytest.raises(FileNotFoundError, match=r"sequence\(s\) \(abandonedfactory/Easy/P000\) "
                                              "are all outside the official loader's 17 test"):
    registry.get_sequences("tartanair", tmp_path, "test")
  shutil.rmtree(tmp_path / "TartanAir")
  _tartanair(tmp_path, np.random.default_rng(0), [("gascola", "Easy", "P001")], n=2)
  with pytest.raises(FileNotFoundError, match="are all official test sequences"):
    registry.get_sequences("tartanair", tmp_path, "train")


def test_links_to_missing_folders_are_named_not_left_out(tmp_path):
  """A TartanAir `<scene>/Hard` or a folder sequence's `disparity/` (or calibration file) that
  is a link to nothing: its sequences were left out, or the sequence read without ground truth
  or calibration, silently."""
  _tartanair(tmp_path, np.random.default_rng(0), [("abandonedfactory", "Easy", "P000"),
                                                  ("abandonedfactory", "Hard", "P001")])
  assert len(registry.get_sequences("tartanair", tmp_path, "train")) == 2
  hard = tmp_path / "TartanAir/abandonedfactory/Hard"
  shutil.rmtree(hard)
  hard.symlink_to(tmp_path / "elsewhere")
  with pytest.raises(FileNotFoundError, match=r"abandonedfactory/Hard: a symbolic link to a "
                     "missing file or folder"):
    registry.get_sequences("tartanair", tmp_path, "train")
  _own_videos(tmp_path / "mine", np.random.default_rng(1))
  lab = tmp_path / "mine/test/lab"
  for name in ("disparity", "calib.txt"):
    moved = tmp_path / f"moved_{name}"
    (lab / name).rename(moved)
    (lab / name).symlink_to(tmp_path / "gone")
    with pytest.raises(FileNotFoundError, match=rf"lab/{name}: a symbolic link to a missing"):
      registry.get_sequences("folder", tmp_path / "mine", "test")
    (lab / name).unlink()
    moved.rename(lab / name)
  assert registry.get_sequences("folder", tmp_path / "mine", "test")[0].has_gt


def test_a_link_to_nothing_above_a_missing_folder_is_named(tmp_path):
  """A folder a reader needs lying behind a link to nothing (Sintel's `camdata_left/`, Spring's
  `train/`) was reported as "directory not found: .../camdata_left/alley_1", or as "no Spring
  data under ...: neither train_frame_left/ nor train/ exists", not as the link it is."""
  _sintel(tmp_path, np.random.default_rng(2))
  cams = tmp_path / "sintel_stereo/training/camdata_left"
  shutil.rmtree(cams)
  cams.symlink_to(tmp_path / "unmounted")
  with pytest.raises(FileNotFoundError, match=r"training/camdata_left: a symbolic link to a "
                     r"missing file or folder, or a loop of links \(.*unmounted\)"):
    registry.get_sequences("sintel_final", tmp_path, "test")
  (tmp_path / "Spring").mkdir()
  (tmp_path / "Spring" / "train").symlink_to(tmp_path / "unmounted")
  with pytest.raises(FileNotFoundError, match=r"Spring/train: a symbolic link to a missing"):
    registry.get_sequences("spring", tmp_path, "test")


def test_training_data_behind_a_link_to_nothing_is_named_not_skipped(tmp_path):
  """KITTI raw images or a VKITTI2 sequence behind a link to nothing (storage not mounted) were
  taken for data not downloaded: the drives and sequences were skipped with a warning that said
  so, and training went on without them."""
  train = ("2011_09_26_drive_0001_sync",)
  _kitti(tmp_path, np.random.default_rng(13), train + ("2011_09_28_drive_0002_sync",), n=1)
  date = tmp_path / "kitti_depth/input/2011_09_26"
  date.rename(tmp_path / "moved")
  date.symlink_to(tmp_path / "unmounted")
  with pytest.raises(FileNotFoundError, match=r"input/2011_09_26: a symbolic link to a missing"):
    registry.get_sequences("kitti_depth", tmp_path, "train")
  _vkitti2(tmp_path, np.random.default_rng(14), ("Scene01_clone", "Scene02_fog"))
  fog = tmp_path / "vkitti2/Scene02/fog"
  shutil.rmtree(fog)
  fog.symlink_to(tmp_path / "unmounted")
  with pytest.raises(FileNotFoundError, match=r"Scene02/fog: a symbolic link to a missing"):
    registry.get_sequences("vkitti2", tmp_path, "train")


def test_long_lists_in_log_lines_are_cut():
  assert base.some_of(list("abc")) == "a, b, c"
  assert base.some_of(list("abcdefgh")) == "a, b, c, d, e, f, ... (2 more)"


def _own_videos(root, rng):
  """Two sequences of the folder layout: PNG16 (KITTI) and PFM ground truth, another naming
  per folder, one with a calibration file, and one without ground truth."""
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  truth = {}
  for seq, n, fmt in (("street", 11, ".png"), ("lab", 3, ".pfm"), ("night", 2, None)):
    base = root / "test" / seq
    truth[seq] = []
    for i in range(n):
      left, right = _rgb(rng), _rgb(rng)
      _png(base / "left" / f"left_{i + 1}.png", left)  # 1 .. 11: natural order, not 1, 10, 11, 2
      _png(base / "right" / f"right_{i + 1:04d}.png", right)
      disp = rng.uniform(1.0, 40.0, (H, W)).astype(np.float32)
      disp[0, 0] = 0.0  # no ground truth there
      if fmt == ".png":
        viz.write_png16(_mkdir(base / "disparity") / f"{i + 1:06d}.png", disp)
        disp = np.round(disp * 256) / 256
      elif fmt == ".pfm":
        disp[1, 0] = np.nan
        viz.write_pfm(_mkdir(base / "disparity") / f"frame{i + 1}.pfm", disp)
      truth[seq].append((left, right, disp if fmt else None))
  (root / "test" / "lab" / "calib.txt").write_text("fx 400\nbaseline 0.2\n")
  return truth


def _npy_sequence(seq, rng, disparities):
  """A sequence of the folder layout at `seq`: random left and right PNG frames and `.npy`
  ground truth, one frame per `{name: disparity}` item, in that order."""
  (seq / "disparity").mkdir(parents=True)
  for name, disp in disparities.items():
    _png(seq / "left" / f"{name}.png", _rgb(rng))
    _png(seq / "right" / f"{name}.png", _rgb(rng))
    np.save(seq / "disparity" / f"{name}.npy", disp)


def _mkdir(path):
  path.mkdir(parents=True, exist_ok=True)
  return path


def test_your_own_videos_in_the_folder_layout(tmp_path, caplog):
  truth = _own_videos(tmp_path / "mine", np.random.default_rng(21))
  seqs = registry.get_sequences("folder", tmp_path / "mine", "test")
  assert [s.name for s in seqs] == ["lab", "night", "street"]
  lab, night, street = seqs
  assert street.sparse and not lab.sparse and len(street) == 11
  assert lab.depth2disp_scale == pytest.approx(80.0) and street.depth2disp_scale is None
  assert not night.has_gt and night[1]["disparity"] is None
  for seq, frames in (("street", street), ("lab", lab)):
    for i, (left, right, disp) in enumerate(truth[seq]):
      f = frames[i]  # frame 10 is left_10.png, not left_2.png
      np.testing.assert_array_equal(f["left"], left)
      np.testing.assert_array_equal(f["right"], right)
      valid = np.isfinite(disp) & (disp > 0)
      np.testing.assert_array_equal(f["valid"], valid)
      np.testing.assert_allclose(f["disparity"][valid], disp[valid], rtol=1e-6)
      assert (f["disparity"][~valid] == 0).all()
  clips = registry.get_training_clips("folder", tmp_path / "mine", frames=2, split="test", seed=3)
  rng, expect = np.random.default_rng(3), []
  for seq in seqs:  # the official strided clips
    for ref in range(0, len(seq), 3):
      k = int(rng.integers(1, 6))
      if ref + 2 * k < len(seq):
        expect.append((seq.name, [ref, ref + k]))
  assert [(c.sequence.name, c.indices) for c in clips] == expect
  assert registry.dataset_folders("folder", tmp_path / "mine") == [  # val/ and train/ to be
      tmp_path / "mine" / s for s in ("train", "val", "test")]      # made: where it would read
  (tmp_path / "mine/test/lab/calib.txt").write_text("fx 400\nbaseline 0.2\ndoffs 12\n")
  with caplog.at_level(logging.WARNING):  # depth = fx B / (d + doffs): no scale, no refusal
    lab = registry.get_sequences("folder", tmp_path / "mine", "test")[0]
  assert lab.depth2disp_scale is None and "doffs 12 px: depth is not fx * baseline" in caplog.text
  with pytest.raises(FileNotFoundError, match=r"no train/ folder in .*mine \(it has test of "
                                              r"train, val, test\)"):
    registry.get_sequences("folder", tmp_path / "mine", "train")
  # A root one level off the layout is told where the dataset's folder is.
  mine = tmp_path / "mine"
  for root, hint in ((mine / "test", f"; {mine / 'test'} holds the sequences: give the folder "
                                     f"above it, {mine}"),
                     (mine / "test" / "lab", f"; {mine / 'test' / 'lab'} is a sequence: give "
                                             f"the dataset's folder, {mine}"),
                     (mine / "test" / "lab" / "left", "")):
    with pytest.raises(FileNotFoundError) as info:
      registry.get_sequences("folder", root, "test")
    assert str(info.value).endswith("<split>/<sequence>/left, right[, disparity]" + hint), info.value
  loose = tmp_path / "loose"  # sequences not in a split folder yet
  shutil.copytree(mine / "test" / "lab", loose / "lab")
  for root, hint in ((loose, f"; {loose} holds the sequences: put them in {loose}/test/"),
                     (loose / "lab", f"; {loose / 'lab'} is a sequence: put it in {loose}/test/ "
                                     f"and give {loose}")):
    with pytest.raises(FileNotFoundError) as info:
      registry.get_sequences("folder", root, "test")
    assert str(info.value).endswith(hint), info.value
  (tmp_path / "mine/test/street/right/right_0011.png").unlink()
  with pytest.raises(ValueError, match=r"folder test/street: frame counts differ.*'right' lacks "
                                       r"frame 11"):
    registry.get_sequences("folder", tmp_path / "mine", "test")
  np.save(tmp_path / "mine/test/lab/disparity/frame9.npy", np.ones((H, W), np.float32))
  with pytest.raises(ValueError, match=r"lab/disparity: disparity files of several formats "
                                       r"\(\.npy, \.pfm\)"):
    registry.get_sequences("folder", tmp_path / "mine", "test")


def test_a_reader_of_your_own_layout_is_registered(tmp_path, monkeypatch):
  for name in ("_LOADERS", "_FOLDERS", "SPLITS", "EVAL_FRAMES"):
    monkeypatch.setattr(registry, name, dict(getattr(registry, name)))
  for name in ("DATASETS", "STRIDED", "_SCENEFLOW"):
    monkeypatch.setattr(registry, name, getattr(registry, name))
  _own_videos(tmp_path / "OwnSet", np.random.default_rng(22))
  registry.register_dataset("own", _load_own, splits=("test",), folders=("OwnSet",),
                            training="sceneflow", eval_frames=2)
  assert "own" in registry.DATASETS and registry.SPLITS["own"] == ("test",)
  # the package's name for the list too (it was the tuple of the import, without "own")
  assert sav_jax.data.DATASETS == registry.DATASETS and "DATASETS" in dir(sav_jax.data)
  seqs = registry.get_sequences("own", tmp_path, "test")  # the datasets root: OwnSet/ in it
  assert [(s.name, s.dataset, len(s)) for s in seqs] == [("lab", "own", 2), ("night", "own", 2),
                                                        ("street", "own", 2)]  # eval_frames
  clips = registry.get_training_clips("own", tmp_path / "OwnSet", frames=2, split="test")
  assert [c.indices for c in clips if c.sequence.name == "lab"] == [[0, 1], [2, 1]]  # sceneflow
  registry.register_dataset("own", _load_own, splits=("test",), folders=("OwnSet",),
                            training="sceneflow", eval_frames=2)  # again, as it is: nothing
  with pytest.raises(ValueError, match="'own' is already registered with other arguments"):
    registry.register_dataset("own", _load_own, splits=("test",))  # another registration
  with pytest.raises(ValueError, match="name must be a new identifier"):  # a built-in reader
    registry.register_dataset("sintel_clean", _load_own, splits=("test",))
  with pytest.raises(ValueError, match="training must be 'strided', 'sceneflow' or None"):
    registry.register_dataset("own2", _load_own, splits=("test",), training="random")
  # a name for a tuple was taken letter by letter (folders O/, w/, n/, ...: never found)
  with pytest.raises(ValueError, match=r"folders must be a tuple of folder names, got 'OwnSet' "
                                       r"\(one folder: folders=\('OwnSet',\)\)"):
    registry.register_dataset("own2", _load_own, splits=("test",), folders="OwnSet")
  for folders in (("OwnSet", 3), ("",), None):
    with pytest.raises(ValueError, match="folders must be a tuple of folder names"):
      registry.register_dataset("own2", _load_own, splits=("test",), folders=folders)
  # a reader without the dataset keyword failed only when first read (a TypeError inside)
  def two_args(root, split):
    return _load_own(root, split, "own2")
  with pytest.raises(ValueError, match=re.escape(
      "load_sequences must take (folder, split, dataset=name), as sav_jax.data.stereo_folder."
      "load_sequences does; two_args(root, split) does not")):
    registry.register_dataset("own2", two_args, splits=("test",))
  with pytest.raises(ValueError, match=re.escape("<lambda>(root) does not")):
    registry.register_dataset("own2", lambda root: [], splits=("test",))
  assert "own2" not in registry.DATASETS
  registry.register_dataset("own3", _load_own, splits=("test",), folders=("OwnSet",),
                            training=None)  # evaluation only: training on it says why not
  with pytest.raises(ValueError, match=r"'own3' was registered with training=None, for "
                                       r"evaluation only: register it with training="):
    registry.get_training_clips("own3", tmp_path, frames=2, split="test")


def test_a_registered_datasets_eval_cut_is_of_its_test_split_only(tmp_path, monkeypatch):
  for name in ("_LOADERS", "_FOLDERS", "SPLITS", "EVAL_FRAMES"):
    monkeypatch.setattr(registry, name, dict(getattr(registry, name)))
  for name in ("DATASETS", "STRIDED", "_SCENEFLOW"):
    monkeypatch.setattr(registry, name, getattr(registry, name))
  rng = np.random.default_rng(24)
  for split in ("val", "test"):
    for side in ("left", "right"):
      for i in range(3):
        _png(tmp_path / "Own" / split / "s" / side / f"{i}.png", _rgb(rng))
  registry.register_dataset("own", _load_own, splits=("val", "test"), folders=("Own",),
                            eval_frames=2)
  assert len(registry.get_sequences("own", tmp_path, "test")[0]) == 2  # the first L frames
  assert len(registry.get_sequences("own", tmp_path, "val")[0]) == 3  # other splits whole
  assert len(registry.get_sequences("own", tmp_path, "test", max_frames=None)[0]) == 3
  assert len(registry.get_sequences("own", tmp_path, "test", max_frames=0)[0]) == 3  # whole
  assert [c.indices for c in registry.get_consecutive_clips("own", tmp_path, 1, "test")] == [
      [0], [1]]  # the validation's clips: of the evaluated frames too
  assert len(registry.get_consecutive_clips("own", tmp_path, 1, "test", max_frames=None)) == 3
  with pytest.raises(ValueError, match="already registered with other arguments"):  # not kept
    registry.register_dataset("own", _load_own, splits=("val", "test"), folders=("Own",),
                              eval_frames=3)
  with pytest.raises(ValueError, match="eval_frames must be an integer > 0"):
    registry.register_dataset("own2", _load_own, splits=("test",), eval_frames=0)
  with pytest.raises(ValueError, match="frames must be an int >= 1"):
    registry.get_consecutive_clips("own", tmp_path, 0, "test")
  seq = registry.get_sequences("own", tmp_path, "val")[0]
  assert len(seq.head(2)) == 2 and len(seq) == 3  # a copy: the sequence stays whole
  (tmp_path / "more" / "spring").mkdir(parents=True)  # a dataset's other folder name
  assert base.find_root(tmp_path / "more", "Spring", "spring") == tmp_path / "more" / "spring"


def test_folder_dataset_unpadded_npy_ground_truth_json_calibration_empty_split(tmp_path):
  rng = np.random.default_rng(25)
  seq = tmp_path / "val" / "cam"
  # 1 .. 11 unpadded in every folder: matched in natural order
  _npy_sequence(seq, rng, {i: np.full((H, W), float(i), np.float32) for i in range(1, 12)})
  (seq / "calib.json").write_text('{"fx": 400, "baseline": 0.25}')
  for i in (1, 2):  # JPEG frames on both sides, named as cameras and tools name them
    for side, ext in (("left", ".jpeg"), ("right", ".JPG")):
      path = tmp_path / "val" / "jpg" / side / f"{i}{ext}"
      path.parent.mkdir(parents=True, exist_ok=True)
      assert cv2.imwrite(str(path), _rgb(rng))
  s, jpg = registry.get_sequences("folder", tmp_path, "val")  # by name
  assert jpg.name == "jpg" and len(jpg) == 2 and jpg[1]["right"].shape == (H, W, 3)
  assert s.depth2disp_scale == pytest.approx(100.0) and not s.sparse  # float GT: dense
  assert [float(s[i]["disparity"][0, 0]) for i in range(11)] == list(range(1, 12))
  np.save(seq / "disparity" / "5.npy", np.ones((H, W, 2), np.float32))
  with pytest.raises(ValueError, match=r"5\.npy: disparity of shape \(8, 12, 2\) .*one channel"):
    s[4]  # pylint: disable=pointless-statement
  (tmp_path / "test").mkdir()
  with pytest.raises(FileNotFoundError, match=r"no sequences in .*test"):
    registry.get_sequences("folder", tmp_path, "test")
  (seq / "calib.json").write_text('{"fx": 400}')
  with pytest.raises(ValueError, match=r"calib\.json: no baseline"):
    registry.get_sequences("folder", tmp_path, "val")
  # A calibration for another image size is refused, as sav-jax infer --calib refuses it (its
  # fx for frames of twice the size gave every depth twice its value, and TCC changed)
  (seq / "calib.json").write_text(f'{{"fx": 800, "baseline": 0.25, "width": {2 * W}}}')
  with pytest.raises(ValueError, match=rf"calib\.json: the calibration is for images of width "
                                       rf"{2 * W}, the frames' width is {W}: .*left.1\.png"):
    registry.get_sequences("folder", tmp_path, "val")
  (seq / "calib.json").write_text('{"fx": 800, "baseline": 0.25, "cx": 20.5, "cy": 7.5}')
  with pytest.raises(ValueError, match=r"calib\.json: the calibration's principal point "
                                       r"\(cx 20\.5, cy 7\.5\) is outside the 8x12"):
    registry.get_sequences("folder", tmp_path, "val")
  (seq / "calib.json").write_text(f'{{"fx": 400, "baseline": 0.25, "width": {W}, "height": {H},'
                                  f' "cx": 5.5, "cy": 3.5}}')
  assert registry.get_sequences("folder", tmp_path, "val")[0].depth2disp_scale == 100.0
  # Both files: the same scale reads; different ones were calib.txt's, calib.json unread
  (seq / "calib.txt").write_text("fx 400\nbaseline 0.25\n")
  assert registry.get_sequences("folder", tmp_path, "val")[0].depth2disp_scale == 100.0
  (seq / "calib.txt").write_text("fx 400\nbaseline 250\n")  # millimetres
  with pytest.raises(ValueError, match=r"cam: calib\.txt and calib\.json give different "
                                       r"depth-to-disparity scales \(fx \* baseline: 100000, "
                                       r"100\); keep one calibration file"):
    registry.get_sequences("folder", tmp_path, "val")


def test_folder_disparities_mostly_beyond_512_px_are_warned_once_per_folder(tmp_path):
  # KITTI's d * 256 saved as float .npy: every value but the small ones was left out by the
  # official valid rule without a word (a frame without any: a loss of 0, an EPE of 0).
  rng = np.random.default_rng(26)
  seq = tmp_path / "train" / "cam"
  disp = np.full((H, W), 4.0 * 256, np.float32)
  disp[0, :3] = (0.0, np.nan, 3.0)
  _npy_sequence(seq, rng, {i: disp if i else disp / 256 for i in range(3)})  # frame 0 in pixels
  (s,) = registry.get_sequences("folder", tmp_path, "train")
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert s[0]["valid"].sum() == H * W - 2  # pixels: no warning
  with pytest.warns(UserWarning, match=r"1\.npy: 99% of its non-zero disparities are 512 px "
                                       r"or more \(max 1024\), which the official rule "
                                       r"leaves out .*is it in pixels"):
    frame = s[1]
  assert frame["valid"].sum() == 1 and frame["disparity"][0, 2] == 3.0
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # once per folder
    s.clip(0, 3)


def test_folder_negative_disparities_are_warned_once_per_folder(tmp_path):
  # A -1 "no data" code: the official rule keeps it as ground truth (|d| = 1 px in the
  # metrics), so its pixels were scored without a word.
  rng = np.random.default_rng(27)
  seq = tmp_path / "test" / "cam"
  disps = {i: np.full((H, W), 5.0, np.float32) for i in range(2)}
  disps[0][0, :W // 2], disps[1][0, :W // 2] = 0.0, -1.0  # frame 0: no negative, no warning
  _npy_sequence(seq, rng, disps)
  (s,) = registry.get_sequences("folder", tmp_path, "test")
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    s[0]
  with pytest.warns(UserWarning, match=r"1\.npy: \d+% of its valid disparities are negative "
                                       r"\(min -1\).*not with a negative code such as -1"):
    frame = s[1]
  assert frame["valid"].all() and frame["disparity"][0, 0] == -1.0  # the numbers: unchanged
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # once per folder
    s.clip(0, 2)


def test_folder_negative_warning_counts_valid_pixels_only_and_names_the_folder_once(tmp_path):
  # A -9999 "no data" code is beyond the official cut (not ground truth): no warning for it.
  # One valid negative pixel is warned of, its share and minimum over the valid pixels; the
  # next file of the folder with negatives is not warned of again.
  rng = np.random.default_rng(29)
  seq = tmp_path / "test" / "cam"
  disps = {i: np.full((H, W), 5.0, np.float32) for i in range(3)}
  disps[0][0, :2] = -9999.0
  disps[1][:4] = np.nan  # 48 of the 96 pixels without ground truth
  disps[1][4, :2], disps[1][5, 0] = -9999.0, -2.0  # 1 negative of the 46 valid pixels
  disps[2][0, 0] = -3.0
  _npy_sequence(seq, rng, disps)
  (s,) = registry.get_sequences("folder", tmp_path, "test")
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    s[0]
  with pytest.warns(UserWarning, match=r"1\.npy: 2% of its valid disparities are negative "
                                       r"\(min -2\)"):
    s[1]
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # once per folder, not once per file
    s[2]
  disp = np.full((20, 20), 5.0, np.float32)
  disp[0, 0] = -2.0  # 1 of 400 valid pixels: 0.25%, which was written "0%"
  with pytest.warns(UserWarning, match=r"x\.npy: 0\.2% of its valid disparities are negative"):
    stereo_folder._warn_if_negative(tmp_path / "few" / "x.npy", disp, np.isfinite(disp))


def test_number_key_takes_the_last_number_whole():
  # A camera's digit in the prefix is not the frame number; a stem without digits is its
  # own key; nanosecond timestamps stay apart (a float would merge them).
  assert base.number_key(pathlib.Path("cam1_1701234567.500000.png")) == (
      base.number_key(pathlib.Path("cam0_1701234567.5.png")))
  assert base.number_key(pathlib.Path("cam1_1701234567.000000.png")) != (
      base.number_key(pathlib.Path("cam1_1701234568.000000.png")))
  assert base.number_key(pathlib.Path("first.png")) == "first"
  assert base.number_key(pathlib.Path("left_0012.png")) == 12
  assert base.number_key(pathlib.Path("1701234567.123456789.png")) != (
      base.number_key(pathlib.Path("1701234567.123456788.png")))


def _load_own(root, split, dataset):
  from sav_jax.data import stereo_folder  # pylint: disable=import-outside-toplevel
  return stereo_folder.load_sequences(root, split, dataset)


def test_max_frames_cuts_any_split_and_dynamic_replica_skips_short_sequences(monkeypatch):
  # get_sequences' docstring: an int L cuts every sequence of any split to its first L
  # frames; a Dynamic Replica sequence shorter than L is skipped (the official evaluation's).
  seqs = [base.StereoSequence(name, {"left": ["l.png"] * n, "right": ["r.png"] * n})
          for name, n in (("short", 5), ("long", 20))]
  for dataset in ("dynamic_replica", "vkitti2"):
    monkeypatch.setitem(registry._LOADERS, dataset, lambda root, split, **options: seqs)
  cut = registry.get_sequences("vkitti2", "/nowhere", "train", max_frames=10)
  assert [(s.name, len(s)) for s in cut] == [("short", 5), ("long", 10)]
  cut = registry.get_sequences("dynamic_replica", "/nowhere", "train", max_frames=10)
  assert [(s.name, len(s)) for s in cut] == [("long", 10)]
  whole = registry.get_sequences("dynamic_replica", "/nowhere", "train")  # "official": whole
  assert [(s.name, len(s)) for s in whole] == [("short", 5), ("long", 20)]


def test_dynamic_replica_focal_length_without_a_format_and_in_capitals(tmp_path):
  # PyTorch3D's ViewpointAnnotation defaults intrinsics_format to "ndc_norm_image_bounds"
  # (fx = f * W / 2), and the official conversion compares the format lower-cased.
  from sav_jax.data import dynamic_replica  # pylint: disable=import-outside-toplevel
  size = [480, 640]  # [H, W]: the two formats differ where H != W
  assert dynamic_replica.focal_px({"focal_length": [2.0, 2.5]}, size) == 640.0
  assert dynamic_replica.focal_px({"focal_length": [2.0, 2.5],
                                   "intrinsics_format": "NDC_Isotropic"}, size) == 480.0
  assert dynamic_replica.focal_px({"focal_length": [2.0, 2.5],
                                   "intrinsics_format": "NDC_norm_image_bounds"}, size) == 640.0


def test_folder_disparities_warned_only_when_more_than_half_are_beyond_512_px(tmp_path):
  # "Most" is more than half of the finite non-zero values: half of them large is not warned
  # (0 and NaN are not counted either way).
  from sav_jax.data import stereo_folder  # pylint: disable=import-outside-toplevel
  for name, values, warned in (("half", [0.0, np.nan, 3.0, 5.0, 600.0, 700.0], False),
                               ("most", [0.0, np.nan, 3.0, 600.0, 700.0, 800.0], True)):
    (tmp_path / name).mkdir()
    np.save(tmp_path / name / "0.npy", np.array([values], np.float32))
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      disp, valid = stereo_folder.read_disparity(tmp_path / name / "0.npy")
    assert [str(w.message).split(":")[0] for w in caught] == \
        ([str(tmp_path / name / "0.npy")] if warned else []), name
    np.testing.assert_array_equal(valid, [[v not in (0.0, 600.0, 700.0, 800.0) and v == v
                                           for v in values]])
    np.testing.assert_array_equal(disp, np.where(valid, np.array([values], np.float32), 0))


def test_folder_disparity_of_booleans_is_refused(tmp_path):
  # A mask saved as the disparity would read as 1 px wherever it is set, counted as valid.
  from sav_jax.data import stereo_folder  # pylint: disable=import-outside-toplevel
  np.save(tmp_path / "0.npy", np.ones((2, 3), bool))
  with pytest.raises(ValueError, match=r"0\.npy: disparity of shape \(2, 3\) and dtype bool"):
    stereo_folder.read_disparity(tmp_path / "0.npy")
  np.save(tmp_path / "1.npy", np.array([[0, 7, 600]], np.int16))  # integers are pixels
  disp, valid = stereo_folder.read_disparity(tmp_path / "1.npy")
  np.testing.assert_array_equal(disp, [[0.0, 7.0, 0.0]])
  np.testing.assert_array_equal(valid, [[False, True, False]])


def test_tartanair_test_split_is_the_official_loaders_17_entries():
  # The official TartanAir loader's (scene, difficulty, part) test entries, written out: an
  # entry off by its difficulty moved a sequence between train and test silently.
  from sav_jax.data import tartanair  # pylint: disable=import-outside-toplevel
  official = {
      ("abandonedfactory", "Easy", "P002"), ("abandonedfactory", "Hard", "P002"),
      ("amusement", "Easy", "P007"), ("amusement", "Hard", "P007"),
      ("carwelding", "Hard", "P003"), ("endofworld", "Easy", "P006"),
      ("endofworld", "Hard", "P006"), ("gascola", "Easy", "P001"), ("gascola", "Hard", "P001"),
      ("hospital", "Hard", "P042"), ("office", "Easy", "P006"), ("office", "Hard", "P006"),
      ("office2", "Easy", "P004"), ("office2", "Hard", "P004"), ("oldtown", "Hard", "P006"),
      ("soulcity", "Easy", "P008"), ("soulcity", "Hard", "P008")}
  assert len(tartanair.TEST) == 17 and set(tartanair.TEST) == official


def test_folder_disparity_suffixes_in_capitals_are_read(tmp_path):
  # The format is the suffix's in any case, as the frames' (`.JPG`): `0.NPY` is an .npy file.
  from sav_jax.data import stereo_folder  # pylint: disable=import-outside-toplevel
  with open(tmp_path / "0.NPY", "wb") as f:
    np.save(f, np.array([[0.0, 7.5]], np.float32))
  disp, valid = stereo_folder.read_disparity(tmp_path / "0.NPY")
  np.testing.assert_array_equal(disp, [[0.0, 7.5]])
  np.testing.assert_array_equal(valid, [[False, True]])


def test_folder_frames_named_by_decimal_timestamps_pair_by_the_whole_number(tmp_path):
  # 1 fps timestamps end in .000000: matched by that last group, a right/ folder one frame
  # ahead of left/ (its first frame dropped) was paired with it, frame by frame
  rng = np.random.default_rng(28)
  seq = tmp_path / "test" / "cam"
  for t in range(4):
    _png(seq / "left" / f"{1701234567 + t}.000000.png", _rgb(rng))
    _png(seq / "right" / f"{1701234568 + t}.000000.png", _rgb(rng))
  with pytest.raises(ValueError, match=r"stem mismatch between .*left.1701234567\.000000\.png "
                                       r"and .*right.1701234568\.000000\.png"):
    registry.get_sequences("folder", tmp_path, "test")
  (seq / "right" / "1701234571.000000.png").rename(seq / "right" / "1701234567.000000.png")
  assert len(registry.get_sequences("folder", tmp_path, "test")[0]) == 4


def test_folder_frames_saved_twice_under_one_number_are_refused(tmp_path):
  # PNG and JPEG copies of each frame (or 0001.png beside 1.png) in left/ and right/: every
  # frame was read twice, as two consecutive frames, without a word
  rng = np.random.default_rng(29)
  seq = tmp_path / "test" / "cam"
  for t in range(3):
    for side in ("left", "right"):
      img = _rgb(rng)
      _png(seq / side / f"{side}_{t:04d}.png", img)
      _png(seq / side / f"{side}_{t:04d}.jpg", img)
  with pytest.raises(ValueError, match=r"cam.left: left_0000\.jpg and left_0000\.png are both "
                                       "frame 0"):
    registry.get_sequences("folder", tmp_path, "test")
  for path in seq.rglob("*.jpg"):
    path.unlink()
  assert len(registry.get_sequences("folder", tmp_path, "test")[0]) == 3
  for side in ("left", "right"):  # one number shared by every name is no frame number
    for t in range(3):
      (seq / side / f"{side}_{t:04d}.png").rename(seq / side / f"{'abc'[t]}_v2.png")
  assert len(registry.get_sequences("folder", tmp_path, "test")[0]) == 3


def test_folder_disparity_folder_without_disparity_files_is_named(tmp_path):
  # ground truth in another format (float TIFF): "frame counts differ: 'left_gt' lacks
  # frame 0", neither the folder nor what is in it named
  seq = tmp_path / "test" / "cam"
  _npy_sequence(seq, np.random.default_rng(30), {"0": np.ones((H, W), np.float32)})
  (seq / "disparity" / "0.npy").rename(seq / "disparity" / "0.tif")
  with pytest.raises(FileNotFoundError, match=r"cam.disparity: no disparity files \(expected "
                                              r"\.png, \.pfm, \.npy, \.exr; it has 0\.tif\)"):
    registry.get_sequences("folder", tmp_path, "test")


def test_folder_split_skips_stray_files_and_hidden_folders_and_checks_the_baseline(tmp_path):
  # A README or a notebook's hidden folder next to the sequences is not a sequence; a
  # calibration whose baseline is negative (the cameras swapped) gives no disparity scale.
  _own_videos(tmp_path, np.random.default_rng(27))
  (tmp_path / "test" / "README.txt").write_text("my videos")
  (tmp_path / "test" / ".ipynb_checkpoints").mkdir()
  seqs = registry.get_sequences("folder", tmp_path, "test")
  assert [s.name for s in seqs] == ["lab", "night", "street"]
  (tmp_path / "test" / "lab" / "calib.txt").write_text("fx 400\nbaseline -0.2\n")
  with pytest.raises(ValueError, match=r"calib\.txt: the stereo baseline is -0\.2; it must be "
                                       "positive"):
    registry.get_sequences("folder", tmp_path, "test")
  (tmp_path / "test" / "lab" / "calib.txt").unlink()
  for path in (tmp_path / "test" / "lab" / "right").iterdir():
    path.unlink()
  (tmp_path / "test" / "lab" / "right" / "right.mp4").write_bytes(b"")  # a video, not frames
  with pytest.raises(FileNotFoundError, match=r"lab.right: no PNG or JPEG frames \(it has "
                                              r"right\.mp4: video files are not read"):
    registry.get_sequences("folder", tmp_path, "test")
  left = tmp_path / "test" / "lab" / "left"  # the left folder alike; hidden files unnamed
  for path in left.iterdir():
    path.unlink()
  (left / "left.mov").write_bytes(b"")
  (left / ".DS_Store").write_bytes(b"")
  with pytest.raises(FileNotFoundError, match=r"lab.left: no PNG or JPEG frames \(it has "
                                              r"left\.mov: video files are not read"):
    registry.get_sequences("folder", tmp_path, "test")
  (left / "left.mov").unlink()  # TIFF frames: not videos (the hint spoke of videos)
  (left / "0000.tif").write_bytes(b"")
  with pytest.raises(FileNotFoundError, match=r"lab.left: no PNG or JPEG frames \(it has "
                                              r"0000\.tif: frames are read from \.png, \.jpg, "
                                              r"\.jpeg files\)"):
    registry.get_sequences("folder", tmp_path, "test")
  (left / "0000.tif").unlink()  # nothing but a hidden file: nothing to name
  with pytest.raises(FileNotFoundError, match=r"lab.left: no PNG or JPEG frames$"):
    registry.get_sequences("folder", tmp_path, "test")


@pytest.mark.parametrize("viewpoint,size", [({"focal_length": [True, 2.5]}, [480, 640]),
                                            ({"focal_length": [2.0, 2.5]}, [480, True])])
def test_dynamic_replica_boolean_in_a_numeric_field_is_refused(viewpoint, size):
  # JSON's true is not the number 1: a malformed record, named by its field
  from sav_jax.data import dynamic_replica  # pylint: disable=import-outside-toplevel
  with pytest.raises(TypeError, match=r"field (viewpoint\.focal_length|image\.size) holds 'True', "
                                      "not a number"):
    dynamic_replica.focal_px(viewpoint, size)
