"""`sav-jax infer` end to end (in-process), and every bad input it must refuse.

One compiled shape is shared by all runs: 3 frames of 32x48 (padded to 32x64), iters=2.
"""

import errno
import json
import logging
import os
import pathlib
import re
import shutil
import sys

import cv2
import jax
import numpy as np
import pytest

import sav_jax
from sav_jax import cli, inference, runtime, viz
from sav_jax.data import synthetic
from sav_jax.tools import infer, video_io

T, H, W, ITERS = 3, 32, 48, 2


pytestmark = pytest.mark.usefixtures("fast_compile")


def test_a_checkpoint_saved_on_a_gpu_runs_with_this_machines_settings(tmp_path, variables,
                                                                        caplog):
  """A training run's checkpoint from a GPU with `vit_attention="cudnn"` could not be used on
  a CPU ("needs a CUDA GPU") and no option of infer or eval could change it."""
  stored = sav_jax.SAVConfig(dtype="bfloat16", vit_attention="cudnn", gru_conv="direct",
                             remat=True, remat_policy="dots_saveable", frame_block_mb=64)
  sav_jax.convert.save_variables(tmp_path / "gpu", variables, {"model": stored.to_dict()})
  with caplog.at_level(logging.INFO):
    _, cfg, _ = infer.load_checkpoint(tmp_path / "gpu")
  assert cfg == sav_jax.SAVConfig(dtype="bfloat16")  # the stored dtype stays: --dtype's default
  assert (f"{tmp_path / 'gpu'}: the stored frame_block_mb=64.0, vit_attention='cudnn', "
          "gru_conv='direct' (the saving machine's settings) replaced by this machine's "
          "defaults") in caplog.text  # (remat, which a forward pass never uses: silently)
  caplog.clear()
  trained = sav_jax.SAVConfig(remat=True)  # a training run's checkpoint: nothing to say
  sav_jax.convert.save_variables(tmp_path / "run", variables, {"model": trained.to_dict()})
  with caplog.at_level(logging.INFO, "sav_jax.tools.infer"):
    assert infer.load_checkpoint(tmp_path / "run")[1] == sav_jax.SAVConfig()
  assert "replaced" not in caplog.text
  assert infer.load_checkpoint(tmp_path / "gpu", dtype="float32")[1] == sav_jax.SAVConfig()


@pytest.fixture(scope="module")
def variables(sav_state_dict):
  return sav_jax.convert.params_from_state_dict(sav_state_dict, sav_jax.SAVConfig())


@pytest.fixture(scope="module")
def clip():
  return synthetic.generate_clip(synthetic.SyntheticConfig(frames=T, height=H, width=W,
                                                           max_disparity=6.0, num_objects=2), 0)


@pytest.fixture(scope="module")
def orbax_ckpt(module_tmp_path, variables):
  path = module_tmp_path / "orbax" / "sav"
  sav_jax.convert.save_variables(path, variables, {"model": sav_jax.SAVConfig().to_dict()})
  return path


def _write_frames(folder, frames, ext=".png"):
  folder.mkdir(parents=True, exist_ok=True)
  for i, f in enumerate(frames):
    img = f[..., ::-1] if f.ndim == 3 else f
    assert cv2.imwrite(str(folder / f"{i:04d}{ext}"), img)
  return folder


@pytest.fixture(scope="module")
def folders(module_tmp_path, clip):
  root = module_tmp_path / "frames"
  return (_write_frames(root / "left", clip["left"]), _write_frames(root / "right", clip["right"]))


def _infer(left, right, ckpt, out, *extra):
  return cli.main(["infer", "--left", str(left), "--right", str(right), "--checkpoint", str(ckpt),
                   "--out", str(out), "--iters", str(ITERS), *extra])


def test_folder_all_formats_and_calibration(tmp_path, folders, npz_ckpt, variables, clip):
  out = tmp_path / "out"
  rc = _infer(*folders, npz_ckpt, out, "--format", "png16,npy", "--format", "pfm",
              "--format", "exr", "--fx", "40", "--fy", "50", "--cx", "10", "--cy", "5",
              "--baseline", "0.1", "--doffs", "2")
  assert rc == 0
  v, u = np.mgrid[:H, :W]
  expected = inference.predict_video(variables, clip["left"], clip["right"], iters=ITERS)
  names = [f"{i:04d}" for i in range(T)]
  for i, name in enumerate(names):
    d = expected[i]
    np.testing.assert_array_equal(np.load(out / "disparity" / f"{name}.npy"), d)
    np.testing.assert_array_equal(viz.read_pfm(out / "disparity" / f"{name}.pfm"), d)
    np.testing.assert_array_equal(viz.read_exr(out / "disparity" / f"{name}.exr"), d)
    png = viz.read_png16(out / "disparity" / f"{name}.png")[0]
    stored = np.clip(np.round(d.astype(np.float64) * 256), 1, 65535)  # tiny d > 0 stays valid
    np.testing.assert_array_equal(png, np.where(d > 0, stored / 256, 0))
    z = 4.0 / (d.astype(np.float64) + 2.0)  # fx * baseline / (d + doffs): every pixel
    np.testing.assert_allclose(np.load(out / "depth" / f"{name}.npy"), z, rtol=1e-6)
    xyz, rgb = viz.read_ply(out / "pointclouds" / f"{name}.ply")
    header = (out / "pointclouds" / f"{name}.ply").read_bytes().split(b"end_header")[0]
    assert b"comment axes: x right, y down, z forward" in header
    assert b"comment unit: the baseline's (fx 40 px, baseline 0.1, doffs 2 px)" in header
    assert len(xyz) == H * W  # raster order; OpenCV axes with fy, cx, cy as given
    np.testing.assert_allclose(xyz, np.stack([(u - 10) * z / 40, (v - 5) * z / 50, z],
                                             -1).reshape(-1, 3), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(rgb, clip["left"][i].reshape(-1, 3))
  assert len(video_io.read_video_file(out / "side_by_side.mp4")) == T
  summary = json.loads((out / "summary.json").read_text())
  assert summary["frames"] == T and summary["calibration"] == dict(
      fx=40.0, fy=50.0, cx=10.0, cy=5.0, baseline=0.1, doffs=2.0)
  # Without fy, cx, cy: fy = fx and the principal point at the frame's centre.
  assert infer.CalibrationSpec(fx=40.0, baseline=0.1).resolve(W, H) == infer.Calibration(
      40.0, 40.0, (W - 1) / 2, (H - 1) / 2, 0.1, 0.0)
  run_s = summary["seconds"] - summary["compile_seconds"]  # no compile if another test did it
  assert summary["frames_per_second_without_compile"] == pytest.approx(T / run_s, rel=1e-2)
  assert summary["frames_per_second_without_compile"] >= summary["frames_per_second"] > 0


def test_overwrite_protection(tmp_path, folders, npz_ckpt, capsys):
  out = tmp_path / "out"
  assert _infer(*folders, npz_ckpt, out, "--format", "npy") == 0
  target = out / "disparity" / "0000.npy"
  np.save(target, np.zeros(1))
  capsys.readouterr()
  assert _infer(*folders, npz_ckpt, out, "--format", "npy") == 2
  assert "--overwrite" in capsys.readouterr().err
  assert np.load(target).shape == (1,)  # untouched
  assert _infer(*folders, npz_ckpt, out, "--format", "npy", "--overwrite") == 0
  assert np.load(target).shape == (H, W)


def test_empty_paths_are_refused(tmp_path, capsys, monkeypatch):
  # "" is the current folder: an unset shell variable (--out "$OUT") wrote there.
  monkeypatch.chdir(tmp_path)
  for argv, flag in ((["infer", "--left", "l", "--right", "r", "--checkpoint", "c", "--out", ""],
                      "--out"),
                     (["infer", "--left", "l", "--right", "r", "--checkpoint", "", "--out", "o"],
                      "--checkpoint"),
                     (["convert", "a.npz", ""], "--dst"),
                     (["bench", "--json", ""], "--json"),
                     (["bench", "--json", "  "], "--json")):  # spaces too, as eval refuses
    assert cli.main(argv) == 2
    assert f"error: {flag} is empty; give a path" in capsys.readouterr().err
  assert not any(tmp_path.iterdir())


@pytest.mark.skipif(not os.path.isdir("/sys/kernel"), reason="needs Linux's sysfs")
def test_an_out_where_nothing_can_be_created_is_refused_before_the_run(tmp_path, capsys,
                                                                       folders, npz_ckpt):
  # sysfs refuses new folders even to root, whom os.access lets write anywhere: the run
  # failed after the model had run. (Also a read-only mount.)
  from sav_jax.tools import UsageError, check_output_dir
  with pytest.raises(UsageError, match=r"--out /sys/sav_jax_test/out: (cannot create anything "
                     r"in /sys|no permission to write in /sys)"):
    check_output_dir("/sys/sav_jax_test/out")
  before = sorted(tmp_path.iterdir())
  check_output_dir(tmp_path / "a" / "b")
  assert sorted(tmp_path.iterdir()) == before  # the write test leaves nothing behind
  assert _infer(*folders, npz_ckpt, "/sys/sav_jax_test/out") == 2
  assert "error: --out /sys/sav_jax_test/out: " in capsys.readouterr().err


def test_a_symlinked_output_is_not_written_through(tmp_path):
  # A link in OUT to a file elsewhere: writing the output would replace that file.
  from sav_jax.tools import infer as infer_tool  # pylint: disable=import-outside-toplevel
  mine = tmp_path / "elsewhere.npy"
  mine.write_bytes(b"user data")
  out = tmp_path / "out" / "disparity"
  out.mkdir(parents=True)
  (out / "0000.npy").symlink_to(mine)
  for overwrite in (False, True):
    with pytest.raises(FileExistsError, match=r"0000\.npy is a symbolic link \(to .*elsewhere"):
      infer_tool.check_overwrite([out / "0000.npy"], overwrite)
  assert mine.read_bytes() == b"user data"
  # A linked subfolder: the run would write into (and --overwrite delete in) its target.
  theirs = tmp_path / "their_images"
  theirs.mkdir()
  (theirs / "0000.png").write_bytes(b"user image")
  linked = tmp_path / "out2"
  linked.mkdir()
  (linked / "disparity").symlink_to(theirs)
  for overwrite in (False, True):
    with pytest.raises(FileExistsError, match=r"out2/disparity is a symbolic link \(to "
                       r".*their_images\); move it away"):
      infer_tool.check_overwrite([linked / "disparity" / "0000.png"], overwrite, linked)
  # OUT itself may be a link: its subfolders are checked below it
  (tmp_path / "out3").symlink_to(tmp_path / "out", target_is_directory=True)
  infer_tool.check_overwrite([tmp_path / "out3" / "disparity" / "0001.npy"], False,
                             tmp_path / "out3")
  assert (theirs / "0000.png").read_bytes() == b"user image"


def test_demo_checks_its_checkpoint_before_building_the_clip(tmp_path, capsys, monkeypatch):
  from sav_jax.data import synthetic as synthetic_data  # pylint: disable=import-outside-toplevel

  def too_early(*args, **kwargs):
    raise AssertionError("the synthetic clip was built before the checkpoint was read")

  monkeypatch.setattr(synthetic_data, "generate_clip", too_early)
  assert cli.main(["demo", "--out", str(tmp_path / "d"), "--checkpoint",
                   str(tmp_path / "missing.npz"), "--no-compile-cache"]) == 2
  assert "missing.npz" in capsys.readouterr().err


def test_demo_refuses_a_video_beyond_host_memory_before_building_it(monkeypatch, capsys,
                                                                     tmp_path):
  """`--height 16000 --width 16000`: the generator filled the memory until the process was
  killed; now one line, "out of host memory", status 2."""
  import types  # pylint: disable=import-outside-toplevel

  from sav_jax.data import synthetic as synthetic_data  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(synthetic_data, "generate_clip", lambda *a, **k: 1 / 0)
  monkeypatch.setattr(demo, "_weights", lambda args, dtype: (
      None, types.SimpleNamespace(dtype="float32"), "stand-in weights"))
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 2**30)
  assert cli.main(["demo", "--out", str(tmp_path / "d"), "--frames", "8", "--height", "2048",
                   "--width", "2048", "--no-compile-cache"]) == 2
  err = capsys.readouterr().err
  assert "sav-jax demo: error: out of host memory: a synthetic video of 8 frames" in err, err
  assert len(err.strip().splitlines()) == 1, err


def test_a_symlink_among_an_earlier_demos_files_is_not_written_through(tmp_path):
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  out = tmp_path / "demo"
  (out / "disparity").mkdir(parents=True)
  (out / "metrics.json").write_text(json.dumps({"weights": "random", "synthetic": {"frames": 2},
                                                "metrics": {}}))
  mine = tmp_path / "mine.png"
  mine.write_bytes(b"user data")
  (out / "disparity" / "frame_000001.png").symlink_to(mine)
  with pytest.raises(FileExistsError, match=r"frame_000001\.png is a symbolic link"):
    demo.check_demo_output(out, 2, False)
  assert mine.read_bytes() == b"user data"


def test_demo_output_check_replaces_only_an_earlier_demos_files(tmp_path):
  """What `sav-jax demo` may replace in --out: its own names when an earlier demo wrote them
  (its metrics.json says so, with its frame count), the rest only with --overwrite; the
  earlier demo's frames beyond this run's count are returned to be deleted."""
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  out = tmp_path / "out"
  (out / "disparity").mkdir(parents=True)
  frame = lambda t: out / "disparity" / f"frame_{t:06d}.png"  # noqa: E731
  assert demo.check_demo_output(out, 3, False) == []  # nothing there yet
  frame(0).write_bytes(b"mine")  # no earlier demo: a file of the demo's names is the user's
  with pytest.raises(FileExistsError, match="frame_000000.png"):
    demo.check_demo_output(out, 3, False)
  assert demo.check_demo_output(out, 3, True) == []
  (out / "comparison.mp4").write_bytes(b"mine")
  with pytest.raises(FileExistsError, match="comparison.mp4"):
    demo.check_demo_output(out, 1, False)
  summary = {"weights": "w", "metrics": {}, "synthetic": {"frames": 5}}
  (out / "metrics.json").write_text(json.dumps(summary))
  for t in range(7):
    frame(t).write_bytes(b"x")
  # an earlier demo of 5 frames: frames 3 and 4 were its (stale now), 5 and 6 are not
  assert demo.check_demo_output(out, 3, False) == [frame(3), frame(4)]
  assert demo.check_demo_output(out, 5, False) == []
  with pytest.raises(FileExistsError, match="frame_000005.png"):  # beyond its frames
    demo.check_demo_output(out, 6, False)
  assert demo.check_demo_output(out, 6, True) == []
  frame(5).unlink()
  frame(6).unlink()
  assert demo.check_demo_output(out, 7, False) == []
  # what counts as an earlier demo's metrics.json
  for text, frames in ((json.dumps(summary), 5), ("{not json", None), ("[1, 2]", None),
                       (json.dumps({"weights": "w", "metrics": {}}), None),
                       (json.dumps({**summary, "synthetic": [5]}), 0),
                       (json.dumps({**summary, "synthetic": {"frames": True}}), 0),
                       (json.dumps({**summary, "synthetic": {}}), 0)):
    (out / "metrics.json").write_text(text)
    assert demo._earlier_demo_frames(out) == frames, text  # pylint: disable=protected-access


def test_a_window_that_cannot_run_leaves_no_output_folders(tmp_path, folders, npz_ckpt,
                                                            capsys, monkeypatch):
  """The memory check of the first window runs as it compiles, after the outputs were
  checked: nothing is created in OUT before that window is done (but the run's lock), and
  the folders made for the lock are removed."""
  seen = []

  def too_big(*args, **kwargs):
    seen.extend(p.name for p in out.iterdir())
    raise inference.InsufficientMemoryError("this window needs 99 GB, 8 GB available")
    yield  # pylint: disable=unreachable

  monkeypatch.setattr(inference, "iter_predict_video", too_big)
  out = tmp_path / "new" / "out"
  assert _infer(*folders, npz_ckpt, out, "--fx", "40", "--baseline", "0.1") == 2
  assert "needs 99 GB" in capsys.readouterr().err
  assert seen == [infer.LOCK]
  assert not (tmp_path / "new").exists()


def test_outputs_never_replace_the_inputs(tmp_path, clip, folders, npz_ckpt, orbax_ckpt,
                                          capsys):
  # Input frames in OUT/disparity (the folder the PNG disparities go to) and an input video
  # at OUT/side_by_side.mp4: refused even with --overwrite, and the inputs stay as they were.
  out = tmp_path / "out"
  left = _write_frames(out / "disparity", clip["left"])
  right = _write_frames(tmp_path / "right", clip["right"])
  before = (left / "0000.png").read_bytes()
  assert _infer(left, right, npz_ckpt, out, "--overwrite") == 2
  err = capsys.readouterr().err
  assert "would replace a file of the input" in err and str(left) in err
  assert (left / "0000.png").read_bytes() == before
  assert not (out / "summary.json").exists()
  jpegs = out / "jpg" / "disparity"  # other names: the outputs would go beside them
  jpegs.mkdir(parents=True)
  for t, frame in enumerate(clip["left"]):
    cv2.imwrite(str(jpegs / f"{t:04d}.jpg"), frame[..., ::-1])
  assert _infer(jpegs, right, npz_ckpt, out / "jpg", "--overwrite") == 2
  err = capsys.readouterr().err
  assert "would be written into the input frame folder" in err and str(jpegs) in err, err
  assert sorted(p.suffix for p in jpegs.iterdir()) == [".jpg"] * len(clip["left"])
  video = tmp_path / "v" / "side_by_side.mp4"
  video.parent.mkdir()
  viz.write_video(video, clip["left"])
  before = video.read_bytes()
  assert _infer(video, right, npz_ckpt, video.parent, "--format", "npy", "--overwrite") == 2
  assert "would replace the input" in capsys.readouterr().err
  assert video.read_bytes() == before
  # A calibration file saved as OUT/summary.json (an earlier run's summary, say) was replaced.
  calib = tmp_path / "c" / "summary.json"
  calib.parent.mkdir()
  calib.write_text('{"fx": 40, "baseline": 0.1}')
  assert _infer(folders[0], right, npz_ckpt, calib.parent, "--calib", str(calib),
                "--overwrite") == 2
  err = capsys.readouterr().err
  assert f"output {calib} would replace the input {calib}" in err, err
  assert calib.read_text() == '{"fx": 40, "baseline": 0.1}'
  # a checkpoint folder may hold the outputs (it was refused as "the input frame folder")
  ckpt_dir = tmp_path / "run"
  shutil.copytree(orbax_ckpt, ckpt_dir)
  assert _infer(folders[0], right, ckpt_dir, ckpt_dir, "--format", "npy") == 0
  assert (ckpt_dir / "summary.json").is_file()


def test_unusable_checkpoints_are_refused_before_the_run(tmp_path, folders, variables,
                                                         sav_state_dict, capsys):
  from sav_jax.tools.infer import load_checkpoint  # pylint: disable=import-outside-toplevel
  sd = dict(sav_state_dict)
  sd["cnet.conv1.weight"] = np.full_like(sd["cnet.conv1.weight"], np.nan)  # a diverged run
  np.savez(tmp_path / "nan.npz", **sd)
  assert _infer(*folders, tmp_path / "nan.npz", tmp_path / "out") == 2
  err = capsys.readouterr().err
  assert "cnet.conv1.weight" in err and "NaN or inf" in err and err.count("\n") == 1, err
  assert not (tmp_path / "out").exists()
  bad = jax.tree_util.tree_map(np.asarray, variables)
  bad["params"]["fnet"]["conv1"]["bias"] = np.full_like(bad["params"]["fnet"]["conv1"]["bias"],
                                                        np.inf)
  sav_jax.convert.save_variables(tmp_path / "inf", bad, {"model": sav_jax.SAVConfig().to_dict()})
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"1 parameter\(s\) hold NaN or inf.*"
                     r"\['fnet'\]\['conv1'\]\['bias'\]"):
    load_checkpoint(tmp_path / "inf")
  for stored in ({"model": "abc"}, {"model": [1, 2]}):  # a config there, but not one
    sav_jax.convert.save_variables(tmp_path / "cfg", variables, stored, overwrite=True)
    with pytest.raises(sav_jax.convert.CheckpointError, match="invalid model config"):
      load_checkpoint(tmp_path / "cfg")
  # A config stored before SAVConfig refused a remat_policy without remat still loads.
  old = {**sav_jax.SAVConfig().to_dict(), "remat": False, "remat_policy": "dots_saveable"}
  sav_jax.convert.save_variables(tmp_path / "cfg", variables, {"model": old}, overwrite=True)
  assert load_checkpoint(tmp_path / "cfg")[1].remat_policy is None


def test_frame_names_that_are_not_utf8_are_refused_before_the_run(tmp_path, clip, npz_ckpt,
                                                                  orbax_ckpt, capsys):
  """Latin-1 names (a zip made on Windows): OpenCV's writer crashed the process with a
  segmentation fault after the model had run, leaving a provisional summary and a lock."""
  for side in ("left", "right"):
    folder = bytes(tmp_path / side)
    os.makedirs(folder)
    for i, frame in enumerate(clip[side]):
      ok, data = cv2.imencode(".png", frame[..., ::-1])
      with open(folder + f"/caf\xe9_{i:04d}.png".encode("latin-1"), "wb") as fh:
        fh.write(data.tobytes())
  out = tmp_path / "out"
  assert _infer(tmp_path / "left", tmp_path / "right", npz_ckpt, out) == 2
  err = capsys.readouterr().err
  assert "caf\\udce9_0000.png': the output file (named after --out and the frame)'s name is " \
         "not UTF-8 text (bytes of another encoding at character" in err, err
  assert not out.exists()
  # an input video of such a name (or in a folder of one): OpenCV's reader crashed too
  viz.write_video(tmp_path / "v.mp4", clip["left"])
  video = tmp_path / os.fsdecode(b"l\xe9ft.mp4")
  os.rename(tmp_path / "v.mp4", video)
  assert _infer(video, video, npz_ckpt, out) == 2
  err = capsys.readouterr().err
  assert "l\\udce9ft.mp4': the video file's name is not UTF-8 text" in err, err
  assert not out.exists()
  with pytest.raises(ValueError, match="the video file's name is not UTF-8 text"):
    video_io.video_fps(video)
  # a checkpoint folder of such a name: orbax's TensorStore failed with a traceback
  checkpoint = tmp_path / os.fsdecode(b"ck\xe9")
  shutil.copytree(orbax_ckpt, checkpoint)
  with pytest.raises(ValueError, match="the orbax checkpoint folder's name is not UTF-8 text"):
    infer.load_checkpoint(checkpoint)
  # the writers: a 16-bit PNG and an EXR of any name (OpenCV's imwrite crashed, OpenEXR
  # refused it: read back as "not an OpenEXR file"), a clear error for the video
  odd = tmp_path / os.fsdecode(b"d\xe9.png")
  viz.write_png16(odd, np.full((2, 3), 4.0, np.float32))
  np.testing.assert_array_equal(viz.read_png16(odd)[0], 4.0)
  odd = tmp_path / os.fsdecode(b"d\xe9.exr")
  viz.write_exr(odd, np.full((2, 3), 4.0, np.float32))
  viz.write_exr(tmp_path / "d.exr", np.full((2, 3), 4.0, np.float32))
  assert odd.read_bytes() == (tmp_path / "d.exr").read_bytes()
  np.testing.assert_array_equal(viz.read_exr(odd), 4.0)
  with pytest.raises(ValueError, match="name is not UTF-8 text"):
    viz.write_video(tmp_path / os.fsdecode(b"v\xe9.mp4"), np.zeros((1, 2, 4, 3), np.uint8))


def test_unknown_stored_config_fields_are_named(caplog):
  """A typo in a stored config (`dtpye`) was reported as "no model config stored" and the
  run went on in float32; unknown fields beside known ones were dropped without a word."""
  from sav_jax.tools.infer import config_from_dict  # pylint: disable=import-outside-toplevel
  with caplog.at_level(logging.WARNING):
    cfg = config_from_dict({"model": {"dtpye": "bfloat16"}}, "ckpt")
  assert cfg == sav_jax.SAVConfig()
  assert ("ckpt: the stored model config has fields SAVConfig does not know, ignored: dtpye"
          in caplog.text)
  assert "ckpt: no model config stored (no SAVConfig field in it)" in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    cfg = config_from_dict({"model": {"dtype": "bfloat16", "frame_blok_mb": 4}}, "ckpt")
  assert cfg.dtype == "bfloat16" and "ignored: frame_blok_mb" in caplog.text
  assert "no model config stored" not in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    config_from_dict({"model": sav_jax.SAVConfig().to_dict()}, "ckpt")
  assert not caplog.text


def _contents(folder: pathlib.Path) -> dict:
  """Every file under `folder` (by its path there) with its bytes."""
  return {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_long_videos_stream_through_infer(tmp_path, npz_ckpt, monkeypatch, capsys):
  # 25 frames in sliding windows, the model replaced by a stand-in whose output labels
  # each frame with its index (disparity 12 (i + 1)): every file lands at the right name,
  # the frame sources are read window by window (never the whole video), the colour range
  # of the video comes from all frames, and the 16-bit PNGs' saturation (d > 256 from frame
  # 21 on) is reported.
  n = 25
  labels = np.arange(n, dtype=np.uint8) * 9
  frames = np.broadcast_to(labels[:, None, None, None], (n, 16, 24, 3)).copy()
  left = _write_frames(tmp_path / "left", frames)
  viz.write_video(tmp_path / "right.mp4", frames)
  read = []
  real_getitem = video_io.FrameSource.__getitem__

  def counting_getitem(self, index):
    out = real_getitem(self, index)
    read.append(len(out))
    return out

  def label_model(variables, lw, rw, *, cfg, iters, pads, check_memory, cache, start,
                  keep_from=None):
    value = (np.round(lw[:, 0, 0, 0] / 9).astype(np.float32) + 1) * 12  # 12 (index + 1)
    hp, wp = lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]
    return -np.broadcast_to(value[:, None, None], (len(lw), hp, wp)).copy()

  monkeypatch.setattr(video_io.FrameSource, "__getitem__", counting_getitem)
  monkeypatch.setattr(inference, "_run_window", label_model)
  out = tmp_path / "out"
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, out, "--format", "npy,png16", "--fx",
                "10", "--baseline", "1", "--max-depth", "0.5") == 0
  for i in range(n):
    d = 12.0 * (i + 1)
    np.testing.assert_array_equal(np.load(out / "disparity" / f"{i:04d}.npy"), d)
    assert viz.read_png16(out / "disparity" / f"{i:04d}.png")[0].max() == min(d, 65535 / 256)
    np.testing.assert_allclose(np.load(out / "depth" / f"{i:04d}.npy"), 10 / d, rtol=1e-6)
    xyz, rgb = viz.read_ply(out / "pointclouds" / f"{i:04d}.ply")
    assert len(xyz) == (16 * 24 if 10 / d <= 0.5 else 0)  # --max-depth: frame 0 is at 0.83
    np.testing.assert_array_equal(rgb, labels[i])  # frame i's colours, in every window
  assert max(read) <= 20  # windows (and video batches), never all 25 frames at once
  assert len(video_io.read_video_file(out / "side_by_side.mp4")) == n
  assert not list(out.glob(".disparity_*"))  # the temporary file is gone
  summary = json.loads((out / "summary.json").read_text())
  assert summary["frames"] == n and summary["max_depth"] == 0.5
  saturated = 4 * 16 * 24  # frames 21..24: 264..300 px
  assert summary["png16_saturated_pixels"] == saturated
  # 24 px and more on 24-px-wide frames (frames 1..24): no pixel can match that far.
  assert summary["disparities_beyond_width"] == 24 * 16 * 24
  video = np.broadcast_to(12.0 * np.arange(1, n + 1)[:, None, None], (n, 16, 24))
  lo, hi = viz.disparity_range(video, percentiles=(1.0, 99.0))
  assert summary["video_disparity_range"] == [round(lo, 4), round(hi, 4)]
  captured = capsys.readouterr()
  printed = captured.out
  assert f"side-by-side video colours: {lo:.2f} px (dark) to {hi:.2f} px (bright)" in printed
  # The stand-in's raw values are negative, as swapped views give them: one line, once.
  swapped = [line for line in captured.err.splitlines() if "swapped" in line]
  assert swapped == [
      "sav-jax infer: warning: frames 0..14: 100% of the disparities are below -1 px before "
      "the official abs() (the model's disparities of a left view are positive): are the left "
      "and right views swapped? (Or the weights not trained for this data.) The output is abs() "
      "of these values, which hides it"], captured.err
  assert f"warning: {saturated} disparities above 255.996 px were stored as 255.996" in printed
  assert (f"warning: {24 * 16 * 24} disparities (96.0% of the pixels) are at least the frame "
          "width (24 px), where no pixel has a match") in printed
  assert summary["empty_point_clouds"] == 1  # frame 0, at 0.83 > --max-depth
  assert ("warning: 1 of the 25 point clouds have no point: every pixel's disparity + doffs was "
          "not positive or deeper than --max-depth 0.5 (check the calibration)") in printed
  # Again with --overwrite, 10 frames, .npy only, no calibration: the earlier run's files that
  # this run does not replace (png16, frames 10-24, depth, point clouds) are deleted, so that
  # the folder holds one run's outputs; a file the earlier summary does not list is kept.
  assert set(summary["outputs"]) >= {"disparity/0024.png", "depth/0024.npy",
                                     "pointclouds/0024.ply", "side_by_side.mp4"}
  (out / "disparity" / "notes.txt").write_text("mine")
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, out, "--format", "npy", "--max-frames",
                "10", "--overwrite") == 0
  kept = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
  assert kept == [*(f"disparity/{i:04d}.npy" for i in range(10)), "disparity/notes.txt",
                  "side_by_side.mp4", "summary.json"]
  assert not (out / "depth").exists() and not (out / "pointclouds").exists()  # emptied: gone
  # (set aside as it began to write: 50 maps, 25 depth maps, 25 point clouds and the video)
  assert f"setting aside 101 files of the earlier run in {out / infer.SET_ASIDE}" in (
      capsys.readouterr().out)
  assert not (out / infer.SET_ASIDE).exists()  # deleted once this run's summary was written
  assert not (out / infer.DONE).exists()
  # A --overwrite run that fails midway puts the earlier run's files back and deletes its
  # own (it left two runs' files mixed, the earlier summary replaced by its provisional one).
  before = _contents(out)

  def failing_model(variables, lw, rw, *, start, **kwargs):
    if start > 0:
      raise ValueError("a frame that no longer decodes")
    return label_model(variables, lw, rw, start=start, **kwargs)

  monkeypatch.setattr(inference, "_run_window", failing_model)
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, out, "--format", "npy", "--format",
                "pfm", "--overwrite") == 2
  assert f"the earlier run's files in {out} were put back" in capsys.readouterr().err
  after = _contents(out)
  assert after == before  # frames 0-14 of the failed run (npy and pfm) are gone
  # Into a new folder: a run that fails midway deletes what it wrote (it left its frames so
  # far and a provisional summary, and the next run was refused without --overwrite)
  fresh = tmp_path / "fresh"
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, fresh, "--format", "npy") == 2
  assert not [p for p in fresh.rglob("*") if p.is_file()], list(fresh.rglob("*"))
  assert not (fresh / "disparity").exists() and not (fresh / infer.SET_ASIDE).exists()
  monkeypatch.setattr(inference, "_run_window", label_model)
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, fresh, "--format", "npy") == 0
  monkeypatch.setattr(inference, "_run_window", failing_model)
  # A run killed after setting files aside (no `except` ran): the next run puts them back
  # before it looks at the folder, deleting what the killed run's provisional summary lists.
  written = infer.set_aside(out, [out / "disparity" / "0003.npy", out / "side_by_side.mp4"])
  assert written == 2 and not (out / "disparity" / "0003.npy").exists()
  (out / "summary.json").write_text(json.dumps({"tool": "sav-jax infer", "complete": False,
                                                "outputs": ["disparity/0003.npy",
                                                            "disparity/0000.pfm"]}))
  (out / "disparity" / "0003.npy").write_bytes(b"the killed run's")
  (out / "disparity" / "0000.pfm").write_bytes(b"the killed run's")
  assert infer.put_back(out) == 2
  assert _contents(out) == before
  # A run killed after its complete summary, while deleting what it set aside: never undone
  # (the next run put the earlier files and summary back over the finished run's).
  finished = _contents(out)
  infer.set_aside(out, [out / "disparity" / "0003.npy"])
  (out / "summary.json").write_text(json.dumps({"tool": "sav-jax infer", "complete": True,
                                                "outputs": ["disparity/0003.npy"]}))
  (out / "disparity" / "0003.npy").write_bytes(b"the finished run's")
  assert infer.put_back(out) == 0 and not (out / infer.SET_ASIDE).exists()
  assert (out / "disparity" / "0003.npy").read_bytes() == b"the finished run's"
  (out / infer.DONE).mkdir()  # its rename done, the deletion cut short: finished here
  assert infer.put_back(out) == 0 and not (out / infer.DONE).exists()
  (out / "summary.json").write_bytes(finished[pathlib.Path("summary.json")])
  (out / "disparity" / "0003.npy").write_bytes(finished[pathlib.Path("disparity/0003.npy")])
  infer.set_aside(out, [out / "disparity" / "0003.npy"])  # killed again: the command says so
  monkeypatch.setattr(inference, "_run_window", label_model)
  assert _infer(left, tmp_path / "right.mp4", npz_ckpt, out, "--format", "npy", "--max-frames",
                "5", "--overwrite") == 0
  assert (f"put back 1 files of an earlier run in {out} that an interrupted --overwrite run had "
          "set aside") in capsys.readouterr().out
  assert sorted(p.name for p in (out / "disparity").iterdir()) == [
      *(f"{i:04d}.npy" for i in range(5)), "notes.txt"]
  summary = json.loads((out / "summary.json").read_text())
  assert summary["complete"] is True and summary["tool"] == "sav-jax infer"
  # Only this command's summary is trusted, and of its list only names this command writes:
  # another tool's summary.json (or one edited by hand) deletes nothing.
  (out / "mine.txt").write_text("mine")
  for listing in ({"outputs": ["mine.txt", "disparity/0004.npy"], "complete": True},
                  {"tool": "sav-jax infer", "complete": True,
                   "outputs": ["mine.txt", "disparity/notes.txt", "disparity/../mine.txt"]}):
    (out / "summary.json").write_text(json.dumps(listing))
    assert _infer(left, tmp_path / "right.mp4", npz_ckpt, out, "--format", "npy",
                  "--max-frames", "4", "--overwrite") == 0
    assert (out / "mine.txt").read_text() == "mine"
    assert sorted(p.name for p in (out / "disparity").iterdir()) == [
        *(f"{i:04d}.npy" for i in range(5)), "notes.txt"]
    (out / "disparity" / "0004.npy").touch()  # (kept: its summary was not this command's)


def test_folders_numbered_alike_at_different_places_are_noted(tmp_path, caplog):
  # Left 0000-0002 beside right 0001-0003 (one frame missing at the start of one folder):
  # frames are paired by their order, so every pair was from two moments, silently.
  frame = np.zeros((8, 8, 3), np.uint8)
  cases = {  # (left names, right names): noted?
      "shifted": (["0000", "0001", "0002"], ["0001", "0002", "0003"], True),
      "gap": (["f_1", "f_2", "f_3"], ["f_1", "f_3", "f_4"], True),  # f_2 missing on the right
      "alike": (["0000", "0001", "0002"], ["0000", "0001", "0002"], False),
      "prefixed": (["left_0001", "left_0002"], ["right_0001", "right_0002"], False),
      "middlebury": (["im0"], ["im1"], False),  # numbered differently, nothing in common
      "unnumbered": (["a", "b"], ["b", "a"], False),
      # KITTI's multi-view names: the last number repeats (10, 11, 10, 11) in both folders
      "kitti": (["000000_10", "000000_11", "000001_10", "000001_11"],
                ["000000_10", "000000_11", "000001_10", "000001_11"], False),
      "kitti_shifted": (["000000_10", "000000_11", "000001_10"],
                        ["000000_11", "000001_10", "000001_11"], False),  # repeats: no claim
      "suffixed": (["frame0001_left", "frame0002_left"], ["frame0002_right", "frame0003_right"],
                   True),
      # each camera dropped another frame: the same places, different numbers (was silent)
      "dropped_each": (["0000", "0001", "0002", "0004"], ["0000", "0001", "0003", "0004"], True),
      "counters": (["0000", "0001"], ["1000", "1001"], False),  # two cameras' own counters
      # decimal timestamps, the right folder a frame ahead: each name's last digits are 000000
      "timestamps": (["1701234567.000000", "1701234568.000000"],
                     ["1701234568.000000", "1701234569.000000"], True),
  }
  for case, (left_names, right_names, noted) in cases.items():
    for side, names in (("l", left_names), ("r", right_names)):
      (tmp_path / case / side).mkdir(parents=True)
      for name in names:
        assert cv2.imwrite(str(tmp_path / case / side / f"{name}.png"), frame)
    for read in (video_io.open_stereo, video_io.load_stereo):
      caplog.clear()
      with caplog.at_level(logging.WARNING):
        read(tmp_path / case / "l", tmp_path / case / "r")
      assert ("the frame folders number their frames alike" in caplog.text) == noted, (
          case, caplog.text)
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    video_io.load_stereo(tmp_path / "dropped_each" / "l", tmp_path / "dropped_each" / "r")
  assert ("number their frames alike, but 1 of the 4 pairs join different numbers, the first "
          "left 0002.png with right 0003.png (frame 2 of each folder)") in caplog.text
  # --max-frames: a cut that hides the shift (left 0001.. beside right 0000..) still pairs
  # wrongly, and one that ends before the places that differ pairs right
  for case, max_frames, noted in (("shifted", 1, True), ("dropped_each", 2, False),
                                  ("dropped_each", 3, True)):
    for read in (video_io.open_stereo, video_io.load_stereo):
      caplog.clear()
      with caplog.at_level(logging.WARNING):
        read(tmp_path / case / "l", tmp_path / case / "r", max_frames=max_frames)
      assert ("the frame folders number their frames alike" in caplog.text) == noted, (
          case, max_frames, caplog.text)
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    video_io.open_stereo(tmp_path / "shifted" / "l", tmp_path / "shifted" / "r")
  assert ("left 0001.png is frame 1 of its folder, right 0001.png frame 0 of its; frames are "
          "paired by their order, so left 0001.png is paired with right 0002.png") in caplog.text


def test_frame_sources_check_every_frame_when_opened(tmp_path, clip, caplog):
  left = _write_frames(tmp_path / "left", clip["left"])
  right = _write_frames(tmp_path / "right", clip["right"])
  viz.write_video(tmp_path / "v.mp4", clip["left"])
  lv, rv, names = video_io.open_stereo(left, right)
  arrays = video_io.load_stereo(left, right)
  assert names == arrays[2] and lv.shape == arrays[0].shape
  (tmp_path / "same").symlink_to(left)
  for read in (video_io.open_stereo, video_io.load_stereo):  # a slip in the command line
    with caplog.at_level(logging.WARNING):
      read(left, tmp_path / "same")
    assert f"--left and --right are the same source ({left}): identical views" in caplog.text
    caplog.clear()
  np.testing.assert_array_equal(lv[1:3], arrays[0][1:3])
  np.testing.assert_array_equal(rv[-1], arrays[1][-1])
  # one frame by index, as a sequence: -T is the first, beyond either end an IndexError (-T - 1
  # wrapped around to frame T - 2, T raised numpy's "index 0 is out of bounds for ... size 0")
  resized = video_io.ResizedSource(lv, H, W)
  for source, frames in ((lv, arrays[0]), (resized, arrays[0].astype(np.float32))):
    np.testing.assert_array_equal(source[-T], frames[0])
    np.testing.assert_array_equal(source[np.int64(1)], frames[1])
    for index in (-T - 1, T):
      with pytest.raises(IndexError, match=f"frame index {index} is out of range for {T} frames"):
        source[index]  # pylint: disable=pointless-statement
  video = video_io.FrameSource(tmp_path / "v.mp4")
  whole = video_io.read_video_file(tmp_path / "v.mp4")
  np.testing.assert_array_equal(np.concatenate([video[1:3], video[0:1], video[2:]]),
                                whole[[1, 2, 0, 2]])  # backwards restarts the decoder
  # max_frames=-1 dropped the last frame (a slice's end); keep=None failed at the first read
  for kwargs, message in (({"max_frames": -1}, "max_frames must be an integer >= 1 or None"),
                          ({"max_frames": 2.0}, "got 2.0"), ({"keep": None}, "keep must be an "
                                                             "integer >= 0, got None"),
                          ({"keep": "3"}, "got '3'"), ({"keep": -1}, "got -1")):
    with pytest.raises(ValueError, match=f"^FrameSource: .*{message}"):
      video_io.FrameSource(tmp_path / "v.mp4", **kwargs)
  with pytest.raises(ValueError, match="read_video_file: max_frames must be an integer >= 1"):
    video_io.read_video_file(tmp_path / "v.mp4", max_frames=0)
  assert len(video_io.FrameSource(left, max_frames=np.int64(2), keep=0)) == 2
  (left / "0002.png").write_bytes(b"not a png")  # the last frame: found before any work
  with pytest.raises(ValueError, match="unreadable frame: .*0002.png"):
    video_io.open_stereo(left, right)
  jpeg = cv2.imencode(".jpg", clip["left"][0])[1].tobytes()
  (tmp_path / "cut.jpg").write_bytes(jpeg[:len(jpeg) // 2])
  with pytest.raises(ValueError, match="unreadable frame: .*cut.jpg: truncated JPEG"):
    video_io.read_frame(tmp_path / "cut.jpg", set())


def test_video_source_reads_long_windows_without_decoding_again(tmp_path, monkeypatch):
  """Windows of 80 frames at stride 10 (and the outputs' reads behind them on N devices)
  go back further than 64 frames: the source keeps as many frames as it is told to, so
  the video is decoded once (it restarted from frame 0 for every window before)."""
  n = 120
  frames = np.broadcast_to((np.arange(n, dtype=np.uint8) * 2)[:, None, None, None],
                           (n, 8, 8, 3)).copy()
  viz.write_video(tmp_path / "v.mp4", frames)
  whole = video_io.read_video_file(tmp_path / "v.mp4")
  decodes = []
  real_decode = video_io._decode  # pylint: disable=protected-access

  def counting_decode(*args):
    decodes.append(args)
    return real_decode(*args)

  monkeypatch.setattr(video_io, "_decode", counting_decode)
  for keep, restarts in ((81, 1), (64, 5)):  # 64: once per window
    video, decodes[:] = video_io.FrameSource(tmp_path / "v.mp4", keep=keep), []
    for a in range(0, n - 80 + 1, 10):
      np.testing.assert_array_equal(video[a:a + 80], whole[a:a + 80])
    assert len(decodes) == restarts


def test_read_video_file_checks_the_name_and_every_frame(tmp_path, clip, monkeypatch):
  viz.write_video(tmp_path / "v.mp4", clip["left"])
  got = video_io.read_video_file(tmp_path / "v.mp4", max_frames=2)
  assert got.shape == (2, H, W, 3) and got.dtype == np.uint8
  # The first two frames, RGB, within the codec's loss (mean |error| 4 here; 18 in BGR order),
  # each nearer its own frame than the other one.
  err = lambda a, b: np.abs(a.astype(np.float64) - b).mean()  # noqa: E731
  for i in range(2):
    assert err(got[i], clip["left"][i]) < 8, (i, err(got[i], clip["left"][i]))
    assert err(got[i], clip["left"][i]) < err(got[i], clip["left"][1 - i]), i
  with pytest.raises(FileNotFoundError, match="nope.mp4: no such file"):
    video_io.read_video_file(tmp_path / "nope.mp4")
  (tmp_path / "notes.txt").write_text("not a video")
  with pytest.raises(ValueError, match="notes.txt: expected a frame folder or a video file"):
    video_io.read_video_file(tmp_path / "notes.txt")
  sizes = [(16, 24, 3), (16, 24, 3), (8, 24, 3)]  # a stream whose third frame is smaller
  monkeypatch.setattr(video_io, "_decode", lambda *_: (np.zeros(s, np.uint8) for s in sizes))
  with pytest.raises(ValueError, match="v.mp4: frames differ in size: frame 2 is 8x24 but the "
                                       "first frame frame 0 is 16x24"):
    video_io.read_video_file(tmp_path / "v.mp4")


def test_video_files_and_orbax_checkpoint(tmp_path, clip, orbax_ckpt, variables):
  viz.write_video(tmp_path / "left.mp4", clip["left"], fps=5)
  viz.write_video(tmp_path / "right.mp4", clip["right"], fps=5)
  out = tmp_path / "out"
  assert _infer(tmp_path / "left.mp4", tmp_path / "right.mp4", orbax_ckpt, out,
                "--format", "npy") == 0
  # The output video plays at the input video's rate (it was always 10 fps).
  assert video_io.video_fps(out / "side_by_side.mp4") == 5.0
  assert json.loads((out / "summary.json").read_text())["video_fps"] == 5.0
  left = video_io.read_video_file(tmp_path / "left.mp4")
  right = video_io.read_video_file(tmp_path / "right.mp4")
  expected = inference.predict_video(variables, left, right, iters=ITERS)
  for i in range(T):
    np.testing.assert_array_equal(np.load(out / "disparity" / f"frame_{i:06d}.npy"), expected[i])


def test_resize_runs_the_model_at_the_given_size(tmp_path, clip, npz_ckpt, variables, capsys,
                                                 monkeypatch):
  """--resize HxW (the official demo resizes to 720x1280): the model runs on the resized
  frames; the disparities come back at the input size, in its pixels."""
  big = {k: video_io.resize_frames(clip[k], 2 * H - 1, 2 * W - 1).round().astype(np.uint8)
         for k in ("left", "right")}
  left, right = (_write_frames(tmp_path / k, big[k]) for k in ("left", "right"))
  out = tmp_path / "out"
  assert _infer(left, right, npz_ckpt, out, "--format", "npy", "--resize", f"{H}x{W}",
                "--fx", "40", "--baseline", "0.1") == 0
  assert f"input: {T} frames of {2 * H - 1}x{2 * W - 1} (height x width), run at {H}x{W}" in \
      capsys.readouterr().out
  small = [video_io.resize_frames(big[k].astype(np.float32), H, W) for k in ("left", "right")]
  # A disparity of 1 resized pixel is the distance between neighbouring resized columns in
  # input pixels: (2W - 2) / (W - 1) = 2 with align_corners (the width ratio (2W - 1) / W was
  # 2-3% short at these sizes).
  ramp = video_io.resize_frames(np.broadcast_to(np.arange(2 * W - 1, dtype=np.float32),
                                                (1, 2, 2 * W - 1)), 2, W)
  np.testing.assert_allclose(np.diff(ramp[0, 0]), 2.0, rtol=1e-6)
  assert video_io.align_corners_scale(2 * W - 1, W) == 2.0
  expected = video_io.resize_frames(inference.predict_video(variables, *small, iters=ITERS),
                                    2 * H - 1, 2 * W - 1) * np.float32(2.0)
  got = np.stack([np.load(out / "disparity" / f"{i:04d}.npy") for i in range(T)])
  assert got.shape == (T, 2 * H - 1, 2 * W - 1)
  np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)
  summary = json.loads((out / "summary.json").read_text())
  assert summary["model_size"] == [H, W] and summary["width"] == 2 * W - 1
  assert summary["video_fps"] == 10.0  # frame folders: no rate of their own
  # torch's align_corners=True bilinear, by hand on one row: ends kept, the middle blended
  row = np.array([[[0.0, 10.0, 30.0]]], np.float32)
  np.testing.assert_allclose(video_io.resize_frames(row, 1, 5), [[[0, 5, 10, 20, 30]]])
  for bad in ("0x64", "32", "axb", "32x64x3"):
    with pytest.raises(SystemExit):
      _infer(left, right, npz_ckpt, tmp_path / "bad", "--resize", bad)
    assert "expected HEIGHTxWIDTH" in capsys.readouterr().err
  assert not (tmp_path / "bad").exists()
  # A window too large for the memory: the line names --resize among the remedies.
  from sav_jax.tools import infer as infer_tool  # pylint: disable=import-outside-toplevel

  def too_big(args):
    raise inference.InsufficientMemoryError("a 20-frame window of 2176x3840 (padded) needs ...",
                                            "fewer frames per window (window/stride)")

  monkeypatch.setattr(infer_tool, "run", too_big)
  assert _infer(left, right, npz_ckpt, tmp_path / "big") == 2
  assert capsys.readouterr().err.endswith(  # the command's flags, not Python's arguments
      "needs ...; use fewer frames per window (--window, --stride), --resize HxW, fewer --iters, "
      "--dtype bfloat16 or a device with more memory\n")


def test_windows_at_once_too_big_for_the_host_name_devices(tmp_path, monkeypatch, capsys):
  """CPU devices' windows that do not fit the host together: the line named no --devices."""

  def at_once(args):
    raise inference.InsufficientMemoryError("8 20-frame windows ... at once", "fewer devices",
                                            devices=8)

  monkeypatch.setattr(infer, "run", at_once)
  assert _infer(tmp_path / "l", tmp_path / "r", tmp_path / "c.npz", tmp_path / "o") == 2
  assert capsys.readouterr().err.endswith(
      "at once; use fewer --devices (here 8), fewer frames per window (--window, --stride), "
      "--resize HxW, fewer --iters, --dtype bfloat16 or a device with more memory\n")


def test_grayscale_16bit_converted_with_note(tmp_path, clip, npz_ckpt, caplog):
  grey = [(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.uint16) * 257) for f in clip["left"]]
  left = _write_frames(tmp_path / "l", grey)
  right = _write_frames(tmp_path / "r",
                        [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in clip["right"]])
  with caplog.at_level(logging.WARNING):
    assert _infer(left, right, npz_ckpt, tmp_path / "out", "--format", "npy") == 0
  # once each, naming the first frame (so the view) converted: a grey left view beside a
  # colour right one was not told apart from the reverse
  assert caplog.text.count("grayscale frames converted to RGB") == 1
  assert f"grayscale frames converted to RGB (grey repeated in 3 channels), e.g. {left}" in (
      caplog.text)
  assert caplog.text.count("16-bit frames converted to 8 bits") == 1
  assert f"16-bit frames converted to 8 bits (round(v / 257)), e.g. {left}" in caplog.text
  assert len(list((tmp_path / "out" / "disparity").iterdir())) == T
  lv, rv, names = video_io.load_stereo(left, right, max_frames=2)
  assert lv.shape == rv.shape == (2, H, W, 3) and names == ["0000", "0001"]
  np.testing.assert_array_equal(lv[0, ..., 0], np.round(grey[0] / 257))
  assert "below 4096" not in caplog.text  # these use the 16-bit range
  # 12-bit data in 16-bit files comes out nearly black: said (it was not).
  notes = set()
  frame = video_io.to_rgb8((grey[0] // 16).astype(np.uint16), "twelve.png", notes)
  assert frame.max() <= 16
  assert any("only values below 4096 (10- or 12-bit data?), e.g. twelve.png" in n for n in notes)
  video_io.to_rgb8((grey[1] // 16).astype(np.uint16), "other.png", notes)  # one note a kind
  assert len([n for n in notes if "below 4096" in n]) == 1
  # 8-bit values in 16-bit files come out black: named as such, with a file.
  video_io.to_rgb8((grey[0] // 257).astype(np.uint16), "eight.png", notes)
  assert any("hold only values 0..255 (8-bit data saved as 16-bit?), e.g. eight.png" in n
             for n in notes)


def test_16bit_rgba_frames_convert_exactly_without_a_float_copy():
  """Every 16-bit value rounds as round(v / 257) (now in integers, the alpha dropped first:
  a float32 copy of four channels took 6.2 GB for a 16000x16000 frame)."""
  values = np.arange(65536, dtype=np.uint16).reshape(256, 256)
  rgba = np.stack([values, values[::-1], values.T, np.full_like(values, 7)], axis=-1)
  notes = set()
  got = video_io.to_rgb8(rgba, "rgba.png", notes)  # OpenCV's BGRA order in, RGB out
  want = np.round(rgba[..., 2::-1].astype(np.float64) / 257).astype(np.uint8)
  np.testing.assert_array_equal(got, want)
  assert any("alpha channel dropped, e.g. rgba.png" in n for n in notes)
  with pytest.raises(ValueError, match=r"two.png: unsupported image shape \(4, 4, 2\)"):
    video_io.to_rgb8(np.zeros((4, 4, 2), np.uint8), "two.png", set())


def test_bfloat16(tmp_path, folders, orbax_ckpt, variables, clip):
  assert _infer(*folders, orbax_ckpt, tmp_path / "out", "--format", "npy", "--dtype",
                "bfloat16") == 0
  got = np.stack([np.load(tmp_path / "out" / "disparity" / f"{i:04d}.npy") for i in range(T)])
  ref = inference.predict_video(variables, clip["left"], clip["right"], iters=ITERS)
  cos = np.sum(got * ref) / (np.linalg.norm(got) * np.linalg.norm(ref))
  assert cos > 0.999, cos  # bfloat16 compute, float32 softmax/upsampling/accumulator
  assert np.abs(got - ref).max() > 1e-4  # and bfloat16 did run (float32 would be equal)
  assert json.loads((tmp_path / "out" / "summary.json").read_text())["dtype"] == "bfloat16"


def _bad_case(name, root, clip, npz_ckpt):
  """(left, right, checkpoint, extra args, expected message) for one bad input."""
  left, right = _write_frames(root / "l", clip["left"]), _write_frames(root / "r", clip["right"])
  if name == "counts":
    (right / "0002.png").unlink()
    return left, right, npz_ckpt, [], f"different frame counts: left has {T} ({left}), " \
        f"right has {T - 1} ({right}); e.g. frame 2 is in the left folder (0002.png), not in " \
        "the right"
  if name == "sizes":
    _write_frames(right, [np.zeros((H, W - 8, 3), np.uint8)] * T)
    return left, right, npz_ckpt, [], f"different frame sizes: left is {H}x{W} ({left}), " \
        f"right is {H}x{W - 8} ({right}) (height x width)"
  if name == "empty":
    (root / "e").mkdir()
    return root / "e", right, npz_ckpt, [], "e: no frames (no .png/"
  if name == "scene_folder":  # the folder above the frames ("was "empty folder"), a GIF
    (root / "scene" / "left").mkdir(parents=True)
    (root / "scene" / "anim.gif").write_bytes(b"GIF89a")
    return root / "scene", right, npz_ckpt, [], "images); it holds 1 folder(s) (left: give " \
        "the one with the frames), 1 other file(s) (anim.gif)"
  if name == "unreadable":
    (left / "0001.png").write_bytes(b"not a png")
    return left, right, npz_ckpt, [], "unreadable frame"
  if name == "mixed_sizes":
    _write_frames(left, [np.zeros((H + 2, W, 3), np.uint8)])
    return left, right, npz_ckpt, [], f"frames differ in size: 0001.png is {H}x{W} but the " \
        f"first frame 0000.png is {H + 2}x{W} (height x width)"
  if name == "no_checkpoint":
    return left, right, root / "missing.pth", [], "checkpoint not found"
  if name == "no_checkpoint_nor_frames":  # named before the frames are opened (and decoded)
    return root / "gone", right, root / "missing.pth", [], "checkpoint not found"
  if name == "incompatible_checkpoint":
    np.savez(root / "bad.npz", **{"fnet.conv1.weight": np.zeros((3, 3), np.float32)})
    return left, right, root / "bad.npz", [], "bad.npz: incompatible checkpoint"
  if name == "vda_checkpoint":
    np.savez(root / "vda.npz", **{"pretrained.cls_token": np.zeros((1, 1, 8), np.float32),
                                  "head.projects.0.weight": np.zeros((4, 8, 1, 1), np.float32)})
    return left, right, root / "vda.npz", [], "not a Stereo Any Video one; `sav-jax convert --vda`"
  if name == "not_a_checkpoint_dir":
    (root / "dir").mkdir()
    return left, right, root / "dir", [], "not a sav-jax checkpoint"
  if name == "not_a_video":
    (root / "l.txt").write_text("hello")
    return root / "l.txt", right, npz_ckpt, [], "expected a frame folder or a video file"
  if name == "odd_iters":
    return left, right, npz_ckpt, ["--iters", "1"], "--iters must be an integer >= 2"
  if name == "long_window":  # more frames than the depth prior's temporal attention takes
    return left, right, npz_ckpt, ["--iters", str(ITERS), "--window", "40", "--stride", "10"], \
        "--window must be at most 32 (the depth prior's temporal attention length), got 40"
  if name == "calibration":
    return left, right, npz_ckpt, ["--fx", "100"], "--baseline"
  if name == "doffs_alone":  # not taken for no calibration
    return left, right, npz_ckpt, ["--doffs", "3"], "calibration needs --fx and --baseline"
  if name == "fy_zero":
    return left, right, npz_ckpt, ["--fx", "100", "--fy", "0", "--baseline", "0.1"], "fy must"
  if name == "fps":
    return left, right, npz_ckpt, ["--iters", str(ITERS), "--fps", "0"], "--fps must be"
  if name == "out_is_file":
    (root / "out").write_text("keep")
    return left, right, npz_ckpt, [], "is a file, not a folder"
  if name == "out_is_dangling_link":  # refused at once (mkdir failed after the whole run)
    (root / "out").symlink_to(root / "gone")
    return left, right, npz_ckpt, [], "is a symbolic link to a missing folder"
  if name == "output_is_folder":  # even --overwrite does not replace a folder
    (root / "out" / "side_by_side.mp4").mkdir(parents=True)
    return left, right, npz_ckpt, ["--iters", str(ITERS), "--overwrite"], "is not a file"
  if name == "output_folder_is_file":
    (root / "out").mkdir()
    (root / "out" / "disparity").write_text("keep")
    return left, right, npz_ckpt, [], "disparity is a file, not a folder"
  if name == "calib_folder":
    return left, right, npz_ckpt, ["--calib", str(root)], "is a folder; give the calibration file"
  if name == "principal_point":  # full-resolution intrinsics for small frames
    return left, right, npz_ckpt, ["--fx", "700", "--cx", "600", "--baseline", "0.5"], \
        f"principal point (cx 600, cy {(H - 1) / 2:g}) is outside the {H}x{W} (height x " \
        "width) frames"
  if name == "depth_format_without_calibration":  # it was ignored silently
    return left, right, npz_ckpt, ["--depth-format", "exr"], "--depth-format applies to metric"
  if name == "max_depth_without_calibration":
    return left, right, npz_ckpt, ["--max-depth", "5"], "--max-depth applies to point clouds"
  if name == "max_depth_negative":
    return left, right, npz_ckpt, ["--fx", "9", "--baseline", "1", "--max-depth", "-1"], \
        "--max-depth must be a finite positive number"
  if name == "max_depth_zero":
    return left, right, npz_ckpt, ["--fx", "9", "--baseline", "1", "--max-depth", "0"], \
        "--max-depth must be a finite positive number, got 0.0"
  if name == "max_depth_infinite":  # (as good as no --max-depth: a mistake)
    return left, right, npz_ckpt, ["--fx", "9", "--baseline", "1", "--max-depth", "inf"], \
        "--max-depth must be a finite positive number, got inf"
  if name == "devices_word":
    return left, right, npz_ckpt, ["--devices", "two"], "devices must be a number of local devices"
  if name == "devices_too_many":  # this process has one CPU device; the cache folder not made
    return (left, right, npz_ckpt, ["--devices", "3", "--compile-cache", str(root / "new_cache")],
            "--devices: devices=3, but 1 local cpu device")
  calib = {"calib_no_keys": ('{"left": {"fx": 720}, "baseline_m": 0.1}', "no calibration found"),
           "calib_null": ('{"fx": null, "baseline": 0.1}', "fx must be a number, got None"),
           "calib_units": ("fx: 720\nbaseline: 0.54 m\n", "line 2: baseline must be one number"),
           "calib_no_baseline": ("cam0=[700 0 10; 0 700 8; 0 0 1]\ndoffs=5\n",
                                 "calib.txt: no baseline found (read: cx, cy, doffs, fx, fy)"),
           "middlebury_no_doffs": ("cam0=[700 0 10; 0 700 8; 0 0 1]\nbaseline=190\n",
                                   "a Middlebury calibration (cam0) needs doffs or cam1"),
           "middlebury_size": (f"cam0=[700 0 10; 0 700 8; 0 0 1]\nbaseline=190\ndoffs=3\n"
                               f"width={W * 4}\n",
                               f"for images of width {W * 4}, the frames' width is {W}"),
           "json_size": (json.dumps({"fx": 700, "baseline": 0.5, "height": H * 2}),
                         f"for images of height {H * 2}, the frames' height is {H}"),
           # (NumPy's "divide by zero encountered" came first, a line of its own)
           "kitti_fx_zero": ("P2: 0 0 6 44 0 700 4 0 0 0 1 0\nP3: 0 0 6 -300 0 700 4 0 0 0 1 0\n",
                             "calib.txt: fx must be a finite positive number, got 0")}
  if name in calib:
    text, message = calib[name]
    (root / "calib.txt").write_text(text)
    return left, right, npz_ckpt, ["--calib", str(root / "calib.txt")], message
  raise AssertionError(name)


@pytest.mark.parametrize("name", [
    "counts", "sizes", "empty", "scene_folder", "unreadable", "mixed_sizes", "no_checkpoint",
    "no_checkpoint_nor_frames", "incompatible_checkpoint", "vda_checkpoint",
    "not_a_checkpoint_dir", "not_a_video", "odd_iters", "long_window", "calibration",
    "doffs_alone", "calib_folder", "fy_zero", "fps", "out_is_file", "out_is_dangling_link",
    "output_is_folder", "output_folder_is_file", "calib_no_keys", "calib_null", "calib_units",
    "calib_no_baseline", "middlebury_no_doffs", "middlebury_size", "json_size", "kitti_fx_zero",
    "principal_point", "depth_format_without_calibration", "max_depth_without_calibration",
    "max_depth_negative", "max_depth_zero", "max_depth_infinite", "devices_word",
    "devices_too_many"])
def test_bad_inputs_exit_2_and_write_nothing(tmp_path, clip, npz_ckpt, capsys, name):
  left, right, ckpt, extra, message = _bad_case(name, tmp_path, clip, npz_ckpt)
  out = tmp_path / "out"
  rc = cli.main(["infer", "--left", str(left), "--right", str(right), "--checkpoint", str(ckpt),
                 "--out", str(out), *(extra or ["--iters", str(ITERS)])])
  err = capsys.readouterr().err
  assert rc == 2, err
  assert message in err
  assert err.count("\n") == 1  # one clean line, no traceback
  if name == "out_is_file":
    assert out.read_text() == "keep"
  elif name == "out_is_dangling_link":
    assert out.is_symlink() and not out.exists()
  elif name.startswith("output_"):
    assert sorted(p.name for p in out.iterdir()) == [
        "side_by_side.mp4" if name == "output_is_folder" else "disparity"]
    assert (out / "side_by_side.mp4").is_dir() or (out / "disparity").read_text() == "keep"
  else:
    assert not out.exists()
  assert not (tmp_path / "new_cache").exists()


def test_frame_counts_that_differ_name_both_sources(tmp_path):
  frames = [np.zeros((H, W, 3), np.uint8)] * 3
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames[:2])
  for load in (video_io.load_stereo, video_io.open_stereo):  # (load_stereo raised AttributeError)
    with pytest.raises(ValueError, match=rf"^different frame counts: left has 3 \({left}\), "
                                         rf"right has 2 \({right}\); e.g. frame 2 is in the "
                                         r"left folder \(0002.png\), not in the right$"):
      load(left, right)


def test_frame_folder_names_the_frame_of_another_size(tmp_path):
  frames, wide = [np.zeros((H, W, 3), np.uint8)] * 4, np.zeros((H, W + 2, 3), np.uint8)
  left = _write_frames(tmp_path / "l", frames[:2] + [wide] + frames[:1])
  right = _write_frames(tmp_path / "r", frames)
  with pytest.raises(ValueError, match=rf"l: frames differ in size: 0002.png is {H}x{W + 2} but "
                                       rf"the first frame 0000.png is {H}x{W} \(height x width\)"):
    video_io.load_stereo(left, right)
  lv, _, names = video_io.load_stereo(left, right, max_frames=2)  # the odd frame not read
  assert lv.shape == (2, H, W, 3) and names == ["0000", "0001"]
  with pytest.raises(ValueError, match=rf"left is {H}x{W} \({right}\), right is {H}x{W + 2} "
                                       rf"\({tmp_path / 'r2'}\) \(height x width\)$"):
    video_io.load_stereo(right, _write_frames(tmp_path / "r2", [wide] * 4))


def test_calibration_file(tmp_path, caplog):
  from sav_jax.tools import UsageError
  from sav_jax.tools.infer import read_calibration
  kitti = tmp_path / "calib_cam_to_cam.txt"
  kitti.write_text("calib_time: 09-Jan-2012 13:57:47\n"
                   "P_rect_02: 7.2e+02 0 6.0e+02 4.5e+01 0 7.2e+02 1.8e+02 0 0 0 1 0\n"
                   "P_rect_03: 7.2e+02 0 6.0e+02 -3.4e+02 0 7.2e+02 1.8e+02 0 0 0 1 0\n")
  c = read_calibration(kitti)
  assert c["fx"] == 720 and c["cy"] == 180 and c["baseline"] == pytest.approx(385 / 720)
  assert "width" not in c  # no S_rect_02: any frame size with the principal point inside
  with open(kitti, "a", encoding="utf-8") as f:  # raw KITTI: the rectified image size
    f.write("S_rect_02: 1.242000e+03 3.750000e+02\nS_rect_03: 1.242000e+03 3.750000e+02\n")
  c = read_calibration(kitti)
  assert (c["width"], c["height"]) == (1242, 375)
  own = tmp_path / "own_size.txt"  # the file's own width/height entries take precedence
  own.write_text(kitti.read_text() + "width: 621\nheight: 188\n")
  assert (read_calibration(own)["width"], read_calibration(own)["height"]) == (621, 188)
  from sav_jax.tools.infer import CalibrationSpec  # pylint: disable=import-outside-toplevel
  assert CalibrationSpec(**c).resolve(1242, 375).cx == 600
  with pytest.raises(UsageError, match="for images of width 1242, the frames' width is 621"):
    CalibrationSpec(**c).resolve(621, 188)  # half-size frames: cx 600 lies inside them
  assert c["doffs"] == 0  # KITTI rectifies both cameras to one principal point
  # P matrices of OpenCV's stereoRectify without CALIB_ZERO_DISPARITY: the principal points
  # differ, and depth = fx * B / (d + cx3 - cx2) (was d alone: 3x too deep here)
  kitti.write_text("P2: 100 0 30 0  0 100 19.5 0  0 0 1 0\n"
                   "P3: 100 0 40 -50  0 100 19.5 0  0 0 1 0\n")
  c = read_calibration(kitti)
  assert (c["baseline"], c["doffs"], c["cx"]) == (0.5, 10, 30)
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  assert viz.depth_from_disparity(np.float32(5), c["fx"], c["baseline"], c["doffs"]) == \
      pytest.approx(100 * 0.5 / 15)
  with caplog.at_level(logging.WARNING, "sav_jax.tools.infer"):
    assert not caplog.records
    kitti.write_text("P2: 100 0 30 -50  0 100 19.5 0  0 0 1 0\n"  # the right camera's first
                     "P3: 100 0 30 0  0 100 19.5 0  0 0 1 0\n")
    assert read_calibration(kitti)["baseline"] == 0.5
  assert [r.getMessage() for r in caplog.records] == [
      f"{kitti}: P2 is to the right of P3 (P2[0,3] -50 < P3[0,3] 0): the matrices look "
      "swapped; the disparities are the left view's (--left), so check that --left is P2's "
      "camera"]
  caplog.clear()
  with caplog.at_level(logging.WARNING, "sav_jax.tools.infer"):
    # KITTI's full-size intrinsics (no size in the file) on half-size frames: cx lies inside
    # them, but 47% of the width from their centre
    spec = CalibrationSpec(fx=721.5, baseline=0.54, cx=609.6, cy=172.9)
    assert spec.resolve(1242, 375).cx == 609.6 and not caplog.records  # 1% and 4% off
    assert spec.resolve(621, 187).fx == 721.5
  [record] = caplog.records
  assert record.getMessage().startswith(
      "the calibration's principal point (cx 609.6, cy 172.9) is 48% of the frame from the "
      "centre of the 187x621 (height x width) frames: is it for another image size")
  js = tmp_path / "c.json"
  js.write_text(json.dumps({"fx": 500, "baseline": 0.12}))
  assert read_calibration(js) == {"fx": 500.0, "baseline": 0.12}
  txt = tmp_path / "c.txt"
  txt.write_text("fx = 400\nbaseline: 0.2\ncx 10\n")
  assert read_calibration(txt) == {"fx": 400.0, "baseline": 0.2, "cx": 10.0}
  txt.write_text("# rig 3\nfx\t400  # px\nfy   410\nbaseline:0.2\nname: left camera\n")
  assert read_calibration(txt) == {"fx": 400.0, "fy": 410.0, "baseline": 0.2}
  mb = tmp_path / "calib_middlebury.txt"  # Middlebury 2014 (baseline in mm)
  mb.write_text("cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\n"
                "cam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\n"
                "doffs=131.111\nbaseline=193.001\nwidth=2964\nheight=1988\nndisp=280\n"
                "isint=0\nvmin=31\nvmax=257\ndyavg=0.918\ndymax=1.516\n")
  assert read_calibration(mb) == {"fx": 3997.684, "fy": 3997.684, "cx": 1176.728,
                                  "cy": 1011.728, "baseline": 193.001, "doffs": 131.111,
                                  "width": 2964.0, "height": 1988.0}
  mb.write_text("cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\n"
                "cam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\nbaseline=193.001\n")
  assert read_calibration(mb)["doffs"] == pytest.approx(1307.839 - 1176.728)  # from cam1
  # A byte-order mark (Windows editors) glued itself to the first key, which was dropped
  # (cx: the image centre instead), and a JSON file was refused.
  txt.write_text("cx 10.5\nfx 40\nbaseline 0.1\n", encoding="utf-8-sig")
  assert read_calibration(txt) == {"cx": 10.5, "fx": 40.0, "baseline": 0.1}
  js.write_text(json.dumps({"fx": 500, "baseline": 0.12}), encoding="utf-8-sig")
  assert read_calibration(js) == {"fx": 500.0, "baseline": 0.12}
  txt.write_text("fx 40\nbaseline 0.1\n", encoding="utf-16")  # was read as "no calibration"
  with pytest.raises(ValueError, match=r"calibration file .*c\.txt is not UTF-8 text"):
    read_calibration(txt)
  txt.write_text("fx 400\nbaseline 0.2\nwidth 64\nheight: 32\n")  # any format may say its size
  assert read_calibration(txt) == {"fx": 400.0, "baseline": 0.2, "width": 64.0, "height": 32.0}
  # the principal point may lie anywhere on the frame, [-0.5, size - 0.5] (pixel centres)
  from sav_jax.tools.infer import CalibrationSpec  # pylint: disable=import-outside-toplevel
  assert CalibrationSpec(400.0, 0.2, cx=-0.5, cy=31.5).resolve(64, 32).cx == -0.5
  assert CalibrationSpec(400.0, 0.2, cx=63.5, width=64, height=32).resolve(64, 32).cx == 63.5
  for cx, cy in ((-0.6, 10.0), (63.6, 10.0), (10.0, 31.6)):
    with pytest.raises(UsageError, match="principal point"):
      CalibrationSpec(400.0, 0.2, cx=cx, cy=cy).resolve(64, 32)
  js.write_text('{"fx": ' + "[" * 100_000 + "]" * 100_000 + "}")  # a RecursionError traceback
  with pytest.raises(UsageError, match=r"c\.json: invalid JSON \(the JSON is nested too deeply\)"):
    read_calibration(js)
  js.write_text('{"fx": ' + "9" * 400 + ', "baseline": 0.1}')  # an OverflowError traceback
  with pytest.raises(UsageError, match=r"c\.json: fx must be a number, got '9{40}'"):
    read_calibration(js)
  for line in (": 400", "= 5"):  # no key
    txt.write_text(f"fx 400\n{line}\n")
    with pytest.raises(UsageError, match=f"c.txt, line 2: expected 'key value'.*got '{line}'"):
      read_calibration(txt)


def test_calibration_kitti_grey_cameras(tmp_path):
  """KITTI files hold the grey pair (cameras 0/1) beside the colour one (2/3): the colour pair
  by default, the grey one with `cameras=(0, 1)` / `--calib-cameras 0,1` or where a file has
  only that pair (was refused: "no calibration found"), a missing pair named."""
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import UsageError
  from sav_jax.tools.infer import calibration_from_args, parse_camera_pair, read_calibration
  odometry = tmp_path / "calib.txt"  # KITTI odometry sequence 00 (P0..P3 and Tr)
  rows = {"P0": "718.856 0 607.1928 0 0 718.856 185.2157 0 0 0 1 0",
          "P1": "718.856 0 607.1928 -386.1448 0 718.856 185.2157 0 0 0 1 0",
          "P2": "718.856 0 607.1928 45.38225 0 718.856 185.2157 -0.1130887 0 0 1 0.003779761",
          "P3": "718.856 0 607.1928 -337.2877 0 718.856 185.2157 2.369057 0 0 1 0.004915215"}
  odometry.write_text("".join(f"{k}: {v}\n" for k, v in rows.items()) + "Tr: 1 0 0 0 0 1 0 0\n")
  colour, grey = (read_calibration(odometry, c) for c in (None, (0, 1)))
  assert colour["baseline"] == pytest.approx((45.38225 + 337.2877) / 718.856)  # 0.53233
  assert grey["baseline"] == pytest.approx(386.1448 / 718.856)  # 0.53716
  assert read_calibration(odometry, (2, 3)) == colour
  grey_only = tmp_path / "grey.txt"
  grey_only.write_text(f"P0: {rows['P0']}\nP1: {rows['P1']}\n")
  assert read_calibration(grey_only) == grey
  with pytest.raises(UsageError, match=r"grey.txt: no KITTI matrices of cameras 2,3 \(P_rect_02/"
                                       r"P_rect_03 or P2/P3\); the file has P0, P1"):
    read_calibration(grey_only, (2, 3))
  raw = tmp_path / "calib_cam_to_cam.txt"  # KITTI raw: P_rect_00 .. P_rect_03, S_rect_0*
  raw.write_text("S_rect_00: 1.242e+03 3.75e+02\n"
                 "P_rect_00: 7.2e+02 0 6.0e+02 0 0 7.2e+02 1.8e+02 0 0 0 1 0\n"
                 "P_rect_01: 7.2e+02 0 6.0e+02 -3.9e+02 0 7.2e+02 1.8e+02 0 0 0 1 0\n"
                 "P_rect_02: 7.2e+02 0 6.0e+02 4.5e+01 0 7.2e+02 1.8e+02 0 0 0 1 0\n"
                 "P_rect_03: 7.2e+02 0 6.0e+02 -3.4e+02 0 7.2e+02 1.8e+02 0 0 0 1 0\n")
  assert read_calibration(raw)["baseline"] == pytest.approx(385 / 720)
  assert read_calibration(raw, (0, 1)) == {"fx": 720, "fy": 720, "cx": 600, "cy": 180,
                                           "baseline": pytest.approx(390 / 720), "doffs": 0,
                                           "width": 1242, "height": 375}
  assert parse_camera_pair(" 0, 1") == (0, 1)
  for bad in ("0", "1,1", "2,4", "a,b", "0,1,2"):
    with pytest.raises(argparse.ArgumentTypeError, match="two different KITTI camera numbers"):
      parse_camera_pair(bad)
  as_json = tmp_path / "c.json"
  as_json.write_text('{"fx": 700, "baseline": 0.5}')
  with pytest.raises(UsageError, match=r"c.json: a JSON calibration has no KITTI cameras to "
                                       r"choose \(0,1 given\)"):
    read_calibration(as_json, (0, 1))
  spec = calibration_from_args(argparse.Namespace(calib=str(odometry), calib_cameras=(0, 1)))
  assert spec.baseline == pytest.approx(grey["baseline"])
  with pytest.raises(UsageError, match="--calib-cameras picks the cameras of a KITTI --calib "
                                       "file: give --calib"):
    calibration_from_args(argparse.Namespace(calib=None, calib_cameras=(0, 1), fx=700.0,
                                             baseline=0.5))


def test_calibration_with_unequal_focal_lengths(tmp_path):
  """fx and fy differ (non-square pixels, or frames resized anisotropically): the baseline
  is KITTI's (P2[0,3] - P3[0,3]) / fx, P[0,3] being -fx times the camera's x, never fy; cx,
  cy come from the third column, fy from P[1,1] (Middlebury: cam0's K likewise)."""
  from sav_jax.tools.infer import read_calibration
  kitti = tmp_path / "calib.txt"
  kitti.write_text("P2: 100 0 30 0  0 80 20 0  0 0 1 0\n"
                   "P3: 100 0 30 -50  0 80 20 0  0 0 1 0\n")
  # 50 px / fx 100 = 0.5 (over fy 80 it would be 0.625)
  assert read_calibration(kitti) == {"fx": 100, "fy": 80, "cx": 30, "cy": 20, "baseline": 0.5,
                                     "doffs": 0}
  mb = tmp_path / "calib_mb.txt"  # Middlebury: K = [fx 0 cx; 0 fy cy; 0 0 1], doffs from cam1
  mb.write_text("cam0=[100 0 30; 0 80 20; 0 0 1]\ncam1=[100 0 42.5; 0 80 20; 0 0 1]\n"
                "baseline=160\n")
  assert read_calibration(mb) == {"fx": 100, "fy": 80, "cx": 30, "cy": 20, "baseline": 160,
                                  "doffs": 12.5}


def test_calibration_spec_fills_defaults_on_the_pixel_centre_grid():
  """Fast twin of the check in test_folder_all_formats_and_calibration (a model run): pixel
  centres are at integers, so a 9 x 6 (width x height) frame's centre is (4, 2.5), not
  (4.5, 3); fy defaults to fx; given values (doffs too) are kept as given."""
  from sav_jax.tools.infer import Calibration, CalibrationSpec
  assert CalibrationSpec(fx=40.0, baseline=0.1).resolve(9, 6) == Calibration(
      40.0, 40.0, 4.0, 2.5, 0.1, 0.0)
  assert CalibrationSpec(fx=40.0, baseline=0.1, fy=50.0, cx=1.0, cy=2.0, doffs=3.0).resolve(
      9, 6) == Calibration(40.0, 50.0, 1.0, 2.0, 0.1, 3.0)


def test_demo_random_weights(tmp_path, monkeypatch, capsys):
  from sav_jax.tools import demo
  monkeypatch.setattr(demo, "BUNDLED", tmp_path / "no_bundled_checkpoint")
  predicted, real_predict = [], inference.predict_video
  clips, real_clip = [], synthetic.generate_clip
  monkeypatch.setattr(synthetic, "generate_clip",
                      lambda *a, **kw: clips.append(real_clip(*a, **kw)) or clips[-1])
  views = []  # (left, right) as the model got them

  def predict(variables, left, right, **kw):
    views.append((left, right))
    predicted.append(real_predict(variables, left, right, **kw))
    return predicted[-1]

  monkeypatch.setattr(inference, "predict_video", predict)
  out = tmp_path / "demo"
  (out / "disparity").mkdir(parents=True)
  for name in (f"frame_{T:06d}.png", "frame_000000.png", "mine.png"):  # the user's files
    (out / "disparity" / name).write_bytes(b"old")
  args = ["demo", "--out", str(out), "--frames", str(T), "--height", str(H), "--width", str(W),
          "--iters", str(ITERS)]
  assert cli.main([*args, "--frames", "1"]) == 2  # TEPE and δt would be an empty 0.000
  assert "need --frames >= 2 (the temporal metrics" in capsys.readouterr().err
  assert cli.main(args) == 2  # not an earlier demo's folder: nothing replaced or deleted
  err = capsys.readouterr().err
  assert "frame_000000.png" in err and "--overwrite" in err and err.count("\n") == 1, err
  assert all(p.read_bytes() == b"old" for p in (out / "disparity").iterdir())
  assert not (out / "metrics.json").exists()
  rc = cli.main([*args, "--overwrite"])
  printed = capsys.readouterr().out
  assert rc == 0
  assert "RANDOM (untrained) weights" in printed and "StereoSGBM" in printed
  for name in ("comparison.mp4", "side_by_side.mp4", "metrics.json"):
    assert (out / name).is_file()
  [pred] = predicted  # the frame PNGs hold the model's disparities (x256), not SGBM's
  [(left, right)] = views  # the clip's left view as the model's left (swapped: negative)
  np.testing.assert_array_equal(left, clips[0]["left"])
  np.testing.assert_array_equal(right, clips[0]["right"])
  for t in range(T):
    stored = np.clip(np.round(pred[t].astype(np.float64) * 256), 1, 65535)
    np.testing.assert_array_equal(viz.read_png16(out / "disparity" / f"frame_{t:06d}.png")[0],
                                  np.where(pred[t] > 0, stored / 256, 0))
  # --overwrite replaces the demo's own names only: frame T (the user's) stays.
  assert sorted(p.name for p in (out / "disparity").glob("*.png")) == [
      f"frame_{t:06d}.png" for t in range(T + 1)] + ["mine.png"]
  assert (out / "disparity" / f"frame_{T:06d}.png").read_bytes() == b"old"
  written = json.loads((out / "metrics.json").read_text())
  assert written["dtype"] == "float32" and written["iters"] == ITERS  # what the row measured
  results = written["metrics"]
  assert set(results) == {"Stereo Any Video", "StereoSGBM"}
  assert results["StereoSGBM"]["disp_epe_mean"] < 2.0  # SGBM works on the synthetic scene
  from sav_jax import metrics  # pylint: disable=import-outside-toplevel
  assert results["Stereo Any Video"] == pytest.approx(metrics.eval_sequence(  # the model's row
      pred, clips[0]["disparity"], clips[0]["valid"].astype(np.float32)))
  # An earlier demo's folder is replaced without --overwrite, and the frames that a longer
  # earlier demo wrote (its metrics.json says T + 2) are removed; frame T + 2 is not its.
  summary = json.loads((out / "metrics.json").read_text())
  summary["synthetic"]["frames"] = T + 2
  (out / "metrics.json").write_text(json.dumps(summary))
  for t in (T + 1, T + 2):
    (out / "disparity" / f"frame_{t:06d}.png").write_bytes(b"old")
  assert cli.main(args) == 0
  assert sorted(p.name for p in (out / "disparity").glob("*.png")) == [
      f"frame_{t:06d}.png" for t in range(T)] + [f"frame_{T + 2:06d}.png", "mine.png"]
  # A shorter earlier demo (1 frame): frame 1 is not its, so it is the user's to keep.
  summary["synthetic"]["frames"] = 1
  (out / "metrics.json").write_text(json.dumps(summary))
  (out / "disparity" / "frame_000001.png").write_bytes(b"mine")
  assert cli.main(args) == 2
  assert "frame_000001.png" in capsys.readouterr().err
  assert (out / "disparity" / "frame_000001.png").read_bytes() == b"mine"


def test_demo_outputs_with_a_stand_in_model(tmp_path, monkeypatch, capsys):
  """The demo's files and table around the model (a stand-in predicting a plane, nothing
  compiled): comparison.mp4 is left | ground truth | model | SGBM at 5 frames/s in one
  colour range, side_by_side.mp4 left | model, the PNGs the model's disparities."""
  import types  # pylint: disable=import-outside-toplevel

  from sav_jax import metrics  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  clips, real_clip = [], synthetic.generate_clip
  monkeypatch.setattr(synthetic, "generate_clip",
                      lambda *a, **kw: clips.append(real_clip(*a, **kw)) or clips[-1])
  monkeypatch.setattr(demo, "_weights", lambda args, dtype: (
      None, types.SimpleNamespace(dtype="float32"), "stand-in weights"))
  n = 2  # the fewest frames the temporal metrics take
  plane = np.full((n, H, W), 2.5, np.float32)
  plane[:, :, W // 2:] = 4.0
  plane[1] += 0.5  # each frame's PNG holds its own prediction
  sgbm_calls, real_sgbm = [], demo.stereo_sgbm
  monkeypatch.setattr(demo, "stereo_sgbm", lambda left, right, **kw: sgbm_calls.append(kw)
                      or real_sgbm(left, right, **kw))
  calls = []
  monkeypatch.setattr(inference, "predict_video",
                      lambda *a, **kw: calls.append(kw) or plane.copy())
  out = tmp_path / "demo"
  args = ["demo", "--out", str(out), "--frames", str(n), "--height", str(H), "--width", str(W),
          "--seed", "3"]
  assert cli.main([*args, "--iters", "1"]) == 2 and "iters" in capsys.readouterr().err
  assert cli.main([*args, "--iters", str(ITERS)]) == 0
  [kwargs] = calls
  assert kwargs["iters"] == ITERS and kwargs["cfg"].dtype == "float32"
  [clip] = clips  # the scene asked for: --seed 3, disparities up to W / 8
  expected = real_clip(synthetic.SyntheticConfig(frames=n, height=H, width=W,
                                                 max_disparity=W / 8, seed=3), 0)
  for key in ("left", "right", "disparity"):
    np.testing.assert_array_equal(clip[key], expected[key])
  gt, valid = clip["disparity"], clip["valid"]
  vmin, vmax = viz.disparity_range(gt, valid)
  # SGBM searches a quarter beyond the scene's largest disparity (W / 8, at most 64)
  assert sgbm_calls == [{"max_disparity": min(64.0, W / 8) * 1.25}]
  sgbm = real_sgbm(clip["left"], clip["right"], max_disparity=min(64.0, W / 8) * 1.25)
  panels = [clip["left"], viz.colorize(gt, vmin, vmax, valid=valid),
            viz.colorize(plane, vmin, vmax), viz.colorize(sgbm, vmin, vmax)]
  for name, parts in (("comparison.mp4", panels), ("side_by_side.mp4", panels[::2])):
    cap = cv2.VideoCapture(str(out / name))
    assert cap.get(cv2.CAP_PROP_FPS) == 5.0
    cap.release()
    frames = video_io.read_video_file(out / name).astype(int)
    assert frames.shape == (n, H, len(parts) * W, 3), name
    for i, want in enumerate(parts):  # (mp4v is lossy)
      err = np.abs(frames[:, :, i * W:(i + 1) * W] - want).mean()
      assert err < 8, (name, i, err)
  for t in range(n):
    np.testing.assert_array_equal(viz.read_png16(out / "disparity" / f"frame_{t:06d}.png")[0],
                                  plane[t])
  summary = json.loads((out / "metrics.json").read_text())
  assert summary["weights"] == "stand-in weights" and summary["iters"] == ITERS
  assert summary["synthetic"] == {"frames": n, "height": H, "width": W, "seed": 3}
  assert set(summary["seconds"]) == {"Stereo Any Video", "StereoSGBM"}
  assert all(0 <= v < 120 for v in summary["seconds"].values()), summary["seconds"]
  mine = metrics.eval_sequence(plane, gt, valid.astype(np.float32))
  assert summary["metrics"]["Stereo Any Video"] == pytest.approx(mine)
  assert summary["metrics"]["StereoSGBM"] == pytest.approx(
      metrics.eval_sequence(sgbm, gt, valid.astype(np.float32)))
  printed = capsys.readouterr().out.splitlines()
  assert printed[:2] == ["weights: stand-in weights", f"synthetic video: {n} frames of {H}x{W} "
                         f"(seed 3), iters {ITERS}, float32"]
  head = next(i for i, l in enumerate(printed) if l.startswith("method"))
  assert printed[head].split() == ["method", "EPE", "bad-1px", "%", "TEPE", "δt-1px", "%",
                                   "seconds"]
  row = printed[head + 2]
  assert len(row.split()) == 8 and float(row.split()[7]) >= 0  # and the seconds
  assert row.startswith("Stereo Any Video  ") and row.split()[3:7] == [
      f"{mine[k]:.3f}" for k in ("disp_epe_mean", "disp_epe_bad_1px", "disp_temp_epe_mean",
                                 "disp_temp_epe_bad_1px")], row
  assert printed[head + 3].startswith("StereoSGBM")


def test_compile_cache_folder_option(tmp_path, folders, npz_ckpt, restore_cache_config):
  import logging  # pylint: disable=import-outside-toplevel

  from sav_jax import inference, runtime  # pylint: disable=import-outside-toplevel
  cache = tmp_path / "xla"
  before = (jax.config.jax_compilation_cache_dir, runtime._low_memory_compile,  # pylint: disable=protected-access
            len(logging.getLogger().handlers), logging.getLogger("absl").level)
  # The executables of earlier tests would be reused in this process, and nothing compiled
  # (with only XLA's newer emitters, as in jaxlib 0.11+, --no-low-memory-compile changes
  # no option).
  inference.clear_cache()
  assert _infer(*folders, npz_ckpt, tmp_path / "out", "--compile-cache", str(cache),
                "--no-low-memory-compile") == 0
  assert cache.is_dir() and any(cache.iterdir())  # the program went to the folder given
  assert len(list((tmp_path / "out" / "disparity").glob("*.png"))) == T
  # Called from Python, the command leaves the caller's settings as they were.
  assert (jax.config.jax_compilation_cache_dir, runtime._low_memory_compile,  # pylint: disable=protected-access
          len(logging.getLogger().handlers), logging.getLogger("absl").level) == before


def test_a_compile_cache_folder_whose_name_is_not_utf8_is_refused(tmp_path, folders, npz_ckpt,
                                                                 restore_cache_config, capsys):
  """JAX's cache took it, then failed at the first compile with a TypeError from its C++
  options (a traceback, after the checkpoint had loaded)."""
  cache = tmp_path / os.fsdecode(b"xla\xe9")
  assert _infer(*folders, npz_ckpt, tmp_path / "out", "--compile-cache", str(cache)) == 2
  assert "xla\\udce9': the compilation cache folder's name is not UTF-8 text" in _error_line(capsys)
  assert not os.path.exists(cache) and not (tmp_path / "out").exists()


def test_stereo_sgbm_range_cut_to_the_frame_width(caplog, monkeypatch):
  """OpenCV fails on numDisparities >= width; the baseline searches what the frames allow,
  saying so once per frame width (python -m eval ran it on every sequence)."""
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(demo, "_SGBM_CUTS", set())
  rng = np.random.default_rng(0)
  left = rng.integers(0, 256, (1, 32, 64, 3), dtype=np.uint8)
  right = np.roll(left, -3, axis=2)
  disp = demo.stereo_sgbm(left, right, max_disparity=256)
  assert disp.shape == (1, 32, 64) and np.isfinite(disp).all()
  assert "max disparity 256 cut to 48 for 64-px-wide frames" in caplog.text
  caplog.clear()
  demo.stereo_sgbm(left, right, max_disparity=256)
  assert "cut to" not in caplog.text
  stereo_sgbm = demo.stereo_sgbm
  with pytest.raises(ValueError, match="wider than 16 px"):
    stereo_sgbm(left[:, :, :16], right[:, :, :16])


def test_stereo_sgbm_finds_each_frames_shift(caplog, monkeypatch):
  """Textured frames whose right view is the left one shifted by 3 and 18 px: SGBM's
  disparities (OpenCV's fixed point / 16) are those shifts, the holes at the left border
  filled from the right. --max-disparity 20 searches 32 px (a multiple of 16), no cut on
  64-px-wide frames; 64 is cut to 48.

  OpenCV matches no pixel in the first numDisparities (32) columns; the documented fill,
  min(nearest valid on the left, nearest valid on the right), has nothing on their left, so
  each row's columns 0-31 take the value of its column 32, the first valid one. Measured
  errors: 0.1875 px (frame 0), 0.125 px (frame 1), border included: atol 0.3 px."""
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(demo, "_SGBM_CUTS", set())
  rng = np.random.default_rng(0)
  left = rng.integers(0, 256, (2, 16, 32, 3), dtype=np.uint8)
  left = np.repeat(np.repeat(left, 2, axis=1), 2, axis=2)  # 32x64, 2x2 blocks
  right = np.stack([np.roll(left[0], -3, axis=1), np.roll(left[1], -18, axis=1)])
  made, real_create = [], cv2.StereoSGBM_create
  monkeypatch.setattr(cv2, "StereoSGBM_create", lambda **kw: made.append(kw) or real_create(**kw))
  disp = demo.stereo_sgbm(left, right, max_disparity=20)
  # OpenCV's recommended smoothness penalties for 3 channels, block 5: 8 and 32 * 3 * 5^2
  assert (made[0]["numDisparities"], made[0]["P1"], made[0]["P2"]) == (32, 600, 2400)
  assert disp.shape == (2, 32, 64) and disp.dtype == np.float32
  assert np.median(disp[0]) == 3.0 and np.median(disp[1]) == 18.0
  np.testing.assert_allclose(disp[0], 3.0, atol=0.3)  # (sub-pixel: 1/16 steps)
  np.testing.assert_allclose(disp[1], 18.0, atol=0.3)  # the filled border too
  for t in range(2):  # the left border filled from the right, row by row
    np.testing.assert_array_equal(disp[t, :, :32], np.repeat(disp[t, :, 32:33], 32, axis=1))
  assert "cut to" not in caplog.text
  demo.stereo_sgbm(left[:1], right[:1], max_disparity=64)
  assert "max disparity 64 cut to 48 for 64-px-wide frames" in caplog.text
  with pytest.raises(ValueError, match="block_size must be an odd integer"):
    demo.stereo_sgbm(left, right, block_size=4)


def test_sgbm_arguments_odd_blocks_and_disparities_of_at_least_1():
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  for block, disparity in ((1, 1), (3, 1.0), (5, np.float32(1.5)), (7, 256)):
    demo.check_sgbm_args(disparity, block)
  for block in (0, 2, 4, -1, 3.0, True):
    with pytest.raises(ValueError, match="block_size must be an odd integer >= 1"):
      demo.check_sgbm_args(16, block)
  for disparity in (0.99, 0, -16, np.inf, np.nan, True, "16"):
    with pytest.raises(ValueError, match="max_disparity must be a finite number >= 1"):
      demo.check_sgbm_args(disparity, 5)


def test_resize_frames_with_aligned_corners_and_disparities_back_at_the_input_size():
  """torch's align_corners=True: output pixel i samples the input at i (n - 1) / (m - 1)."""
  ramp = np.arange(0, 30, 10, dtype=np.float32)  # 0, 10, 20
  frames = np.broadcast_to(ramp[None, None, :, None], (2, 2, 3, 3))  # [N, H, W, C]
  up = video_io.resize_frames(frames, 3, 5)
  assert up.shape == (2, 3, 5, 3) and up.dtype == np.float32
  np.testing.assert_allclose(up[1, 2, :, 0], [0, 5, 10, 15, 20])
  column = np.arange(5, dtype=np.float32)[None, :, None] * 4  # 0, 4, .., 16 down the rows
  np.testing.assert_allclose(video_io.resize_frames(column, 3, 1)[0, :, 0], [0, 8, 16])
  same = np.ones((1, 2, 2), np.uint8)
  assert video_io.resize_frames(same, 2, 2).dtype == np.float32
  assert video_io.align_corners_scale(5, 3) == 2.0 and video_io.align_corners_scale(9, 3) == 4.0
  assert video_io.align_corners_scale(4, 1) == 4.0 and video_io.align_corners_scale(1, 4) == 0.25
  assert video_io.align_corners_scale(5, 2) == 4.0 and video_io.align_corners_scale(2, 5) == 0.25
  # a disparity of 1 px on 3-wide frames is 2 px on the 5-wide input
  back = video_io.disparities_to_input_size(np.ones((2, 2, 3), np.float32), 3, 5)
  assert back.shape == (2, 3, 5)
  np.testing.assert_allclose(back, 2.0)
  lazy = video_io.ResizedSource(frames, 3, 5)
  assert len(lazy) == 2 and lazy.shape == (2, 3, 5, 3)
  np.testing.assert_allclose(lazy[-1], up[1])
  np.testing.assert_allclose(lazy[0:2], up)
  with pytest.raises(IndexError, match="frame index 2 is out of range for 2 frames"):
    lazy[2]  # pylint: disable=pointless-statement
  with pytest.raises(IndexError, match="frame index -3 is out of range for 2 frames"):
    lazy[-3]  # pylint: disable=pointless-statement


def test_to_rgb8_conversions_and_their_notes():
  grey = np.array([[0, 7, 255]], np.uint8)
  for img in (grey, grey[..., None]):  # [H, W] and [H, W, 1]: grey repeated, noted
    notes = set()
    out = video_io.to_rgb8(img, "g.png", notes)
    assert out.shape == (1, 3, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, np.repeat(grey[..., None], 3, axis=2))
    assert [n.split(", e.g.")[0] for n in notes] == [
        "grayscale frames converted to RGB (grey repeated in 3 channels)"]
  bgr = np.array([[[1, 2, 3], [4, 5, 6]]], np.uint8)
  notes = set()
  np.testing.assert_array_equal(video_io.to_rgb8(bgr, "c.png", notes), bgr[..., ::-1])
  assert not notes
  # 16 bits: round(v / 257) (128 / 257 = 0.498, 129 / 257 = 0.502, 386 / 257 = 1.502)
  v = np.array([[0, 128, 129, 257, 385, 386, 65535]], np.uint16)
  np.testing.assert_array_equal(video_io.to_rgb8(v, "w.png", set())[..., 0],
                                [[0, 0, 1, 1, 1, 2, 255]])
  for top, note in ((255, "hold only values 0..255"), (256, "below 4096"),
                    (4095, "below 4096"), (4096, None)):
    notes = set()
    video_io.to_rgb8(np.array([[0, top]], np.uint16), "w.png", notes)
    assert [n for n in notes if "some 16-bit" in n and (note is None or note not in n)] == []
    assert any(note in n for n in notes) if note else len(notes) == 2, (top, notes)
  for bad, match in ((np.zeros((2, 2), np.float32), "unsupported pixel type float32"),
                     (np.zeros((2, 2, 2), np.uint8), r"unsupported image shape \(2, 2, 2\)")):
    with pytest.raises(ValueError, match=match):
      video_io.to_rgb8(bad, "x.png", set())


def test_video_files_read_in_order_with_their_rate_and_names_from_str_paths(tmp_path,
                                                                             caplog, monkeypatch):
  levels = (40, 120, 200)  # frame t: grey level levels[t] on the left, its colour on the right
  frames = np.zeros((3, 16, 16, 3), np.uint8)
  for t, level in enumerate(levels):
    frames[t, :, :8] = level
    frames[t, :, 8:, t] = 255
  viz.write_video(tmp_path / "v.mp4", frames, fps=12.5)
  path = str(tmp_path / "v.mp4")
  whole = video_io.read_video_file(path)
  assert whole.shape == (3, 16, 16, 3)
  for t, level in enumerate(levels):  # (mp4v is lossy)
    assert abs(whole[t, :, :8].mean() - level) < 8
    assert whole[t, 4:12, 10:14, t].mean() > 200 and whole[t, 4:12, 10:14].mean() < 140
  source = video_io.FrameSource(path)
  assert len(source) == 3 and source.fps == 12.5 and video_io.video_fps(path) == 12.5
  assert source.notes == set()  # a complete video: no "fewer frames than declared" note
  assert source.names == ["frame_000000", "frame_000001", "frame_000002"]
  np.testing.assert_array_equal(source[-1], whole[2])
  np.testing.assert_array_equal(source[1:3], whole[1:])
  assert source[2:2].shape == (0, 16, 16, 3) and source[2:2].dtype == np.uint8
  with pytest.raises(ValueError, match="FrameSource slices take step 1"):
    source[0:3:2]  # pylint: disable=pointless-statement
  left, right, names = video_io.load_stereo(path, path)
  np.testing.assert_array_equal(left, whole)
  assert names == source.names
  for read in (video_io.load_stereo, video_io.open_stereo):
    with pytest.raises(ValueError, match="--max-frames must be >= 1, got 0"):
      read(path, path, max_frames=0)
  junk = tmp_path / "junk.mp4"
  junk.write_bytes(b"not a video")
  assert video_io.video_fps(junk) is None
  with pytest.raises(ValueError, match="junk.mp4: unreadable video"):
    video_io.read_video_file(junk)
  monkeypatch.setattr(video_io, "_decode", lambda *a: iter(()))  # opens, decodes nothing
  with pytest.raises(ValueError, match="v.mp4: the video has no decodable frames"):
    video_io.read_video_file(path)


def test_disparity_maps_round_trip_in_every_format(tmp_path):
  d = np.array([[0.0, 1.5, 100.25], [3.0, 255.0, 300.0]], np.float32)
  for fmt, suffix in (("png16", ".png"), ("npy", ".npy"), ("pfm", ".pfm"), ("exr", ".exr")):
    path = video_io.disparity_path(tmp_path, "f", fmt)
    assert path == tmp_path / f"f{suffix}"
    assert video_io.write_map(path, d, fmt) == (1 if fmt == "png16" else 0)  # 300 saturates
    back = video_io.read_map(path)
    assert back.dtype == np.float32 and back.shape == (2, 3)
    want = np.minimum(d, 65535 / 256) if fmt == "png16" else d  # (x256 integers: exact here)
    np.testing.assert_array_equal(back, want)
  with pytest.raises(ValueError, match="unknown format 'tiff'"):
    video_io.disparity_path(tmp_path, "f", "tiff")
  with pytest.raises(ValueError, match="unknown format 'tiff'"):
    video_io.write_map(tmp_path / "f.tiff", d, "tiff")
  (tmp_path / "f.txt").write_text("1")
  with pytest.raises(ValueError, match="f.txt: unknown disparity file type"):
    video_io.read_map(tmp_path / "f.txt")


def test_fill_invalid_takes_the_smaller_nearest_valid_value_of_the_row():
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  disp = np.array([[0, 5, 0, 0, 3, 0],      # holes between 5 and 3 get 3; the ends their one
                   [4, 0, 0, -1, 0, 9],     # (-1: SGBM's invalid code too) min(4, 9)
                   [0, 0, 0, 0, 0, 0],      # nothing valid: 0
                   [0, 0, 2, 8, 0, 6],
                   [0.5, 0, 0, 0, 0, 0.25]], np.float32)  # (sub-pixel values are valid)
  want = [[5, 5, 3, 3, 3, 3], [4, 4, 4, 4, 4, 9], [0] * 6, [2, 2, 2, 8, 6, 6],
          [0.5, 0.25, 0.25, 0.25, 0.25, 0.25]]
  filled = demo.fill_invalid(disp)
  assert filled.dtype == np.float32
  np.testing.assert_array_equal(filled, want)
  np.testing.assert_array_equal(demo.fill_invalid(disp[:, ::-1]), np.array(want)[:, ::-1])


@pytest.mark.parametrize("handlers", [0, 1])
def test_command_logging_sets_the_levels_and_restores(monkeypatch, handlers):
  """INFO (DEBUG with --verbose) on the root logger, a stderr handler added only where the
  root has none (basicConfig's rule: a notebook's is kept), JAX's and absl's INFO lines quiet
  unless --verbose; afterwards all as it was."""
  from sav_jax.tools import command_logging  # pylint: disable=import-outside-toplevel
  root, jax_log, absl = (logging.getLogger(n) for n in (None, "jax", "absl"))
  mine = [logging.NullHandler()] * handlers
  monkeypatch.setattr(root, "handlers", list(mine))
  before = (root.level, jax_log.level, absl.level)
  for logger, level in ((root, logging.ERROR), (jax_log, logging.NOTSET), (absl, logging.NOTSET)):
    logger.setLevel(level)
  try:
    for verbose, level in ((False, logging.INFO), (True, logging.DEBUG)):
      with command_logging(verbose):
        assert root.level == level and len(root.handlers) == 1  # the user's, or one to stderr
        quiet = logging.NOTSET if verbose else logging.WARNING  # --verbose shows everything
        assert (jax_log.level, absl.level) == (quiet, quiet)
      assert (root.handlers, root.level, jax_log.level, absl.level) == (
          mine, logging.ERROR, logging.NOTSET, logging.NOTSET)
  finally:
    for logger, level in zip((root, jax_log, absl), before):
      logger.setLevel(level)


@pytest.mark.parametrize("value", ["1", " 1\n", 1, "all", " ALL ", "0", 0])
def test_devices_option_takes_a_number_or_all(value):
  # (this process has one CPU device: 1, "all" and 0 are each that one)
  from sav_jax.tools import resolve_devices_option  # pylint: disable=import-outside-toplevel
  assert resolve_devices_option(value) == jax.local_devices()


@pytest.mark.parametrize("value,name,takes_all,message", [
    ("two", "--devices", True, "--devices: devices must be a number of local devices >= 1, or "
                               "0 or 'all' for every one, got 'two'"),
    ("\u00b2", "--devices", True, "--devices: devices must be a number of local devices >= 1, "
                                   "or 0 or 'all' for every one, got '\u00b2'"),
    (-1, "config.devices", False, "config.devices: devices must be a number of local devices "
                                  ">= 1, or 0 for every one, got -1"),
    (3, "config.devices", False, "config.devices: devices=3, but 1 local cpu device is available"),
])
def test_devices_option_refuses_other_values_naming_the_option(value, name, takes_all, message):
  from sav_jax.tools import UsageError, resolve_devices_option  # pylint: disable=import-outside-toplevel
  with pytest.raises(UsageError, match=f"^{re.escape(message)}$"):
    resolve_devices_option(value, name, takes_all=takes_all)


def test_matmul_precision_option_applies_the_precision_and_names_the_one_in_effect():
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import tools  # pylint: disable=import-outside-toplevel
  p = argparse.ArgumentParser()
  tools.add_matmul_precision_argument(p)
  tools.add_devices_argument(p)
  args = p.parse_args([])
  assert args.matmul_precision is None and args.devices == "1"
  context, name = tools.matmul_precision(args)  # not given: JAX's setting stays
  with context:
    assert jax.config.jax_default_matmul_precision is None
  assert name == "default"
  with jax.default_matmul_precision("high"):  # as JAX_DEFAULT_MATMUL_PRECISION=high sets it
    assert tools.matmul_precision(args)[1] == "high"
  context, name = tools.matmul_precision(p.parse_args(["--matmul-precision", "highest"]))
  with context:
    assert str(jax.config.jax_default_matmul_precision) == "highest"
  assert name == "highest" and jax.config.jax_default_matmul_precision is None


def test_output_folder_check_names_what_is_in_the_way(tmp_path, monkeypatch):
  from sav_jax.tools import UsageError, check_output_dir  # pylint: disable=import-outside-toplevel
  (tmp_path / "f").write_text("keep")
  (tmp_path / "link").symlink_to(tmp_path / "moved")
  assert check_output_dir(str(tmp_path / "new" / "out")) == tmp_path / "new" / "out"
  assert check_output_dir(tmp_path) == tmp_path
  f, link = tmp_path / "f", tmp_path / "link"
  for out, flag, message in (
      (f, "--out", f"--out {f} is a file, not a folder"),
      (f / "out", "--out", f"--out {f / 'out'}: {f} is a file, not a folder"),
      (f, "DST d: folder", f"DST d: folder {f} is a file, not a folder"),
      (f / "out", "DST d: folder", f"DST d: folder {f / 'out'}: {f} is a file, not a folder"),
      (link / "out", "--out", f"--out {link / 'out'}: {link} is a symbolic link to a missing "
                              f"folder ({tmp_path / 'moved'}), or a loop of links")):
    with pytest.raises(UsageError, match=f"^{re.escape(message)}$"):
      check_output_dir(out, *(flag,) * (flag != "--out"))
  assert f.read_text() == "keep" and not (tmp_path / "moved").exists()
  # a folder the user may not write in (os.access says yes to root: asked here)
  monkeypatch.setattr(os, "access", lambda path, mode: mode != os.W_OK | os.X_OK)
  message = f"--out {tmp_path / 'a'}: no permission to write in {tmp_path}"
  with pytest.raises(UsageError, match=f"^{re.escape(message)}$"):
    check_output_dir(tmp_path / "a")


@pytest.mark.parametrize("errors,printed", [("strict", b"caf\\udce9\n"),
                                            ("surrogateescape", b"caf\xe9\n")])
def test_printed_names_that_are_not_utf8(monkeypatch, errors, printed):
  # a UTF-8 locale's stdout shows the name's bytes as \udce9; a C locale's writes the bytes
  import io  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import printable_names  # pylint: disable=import-outside-toplevel
  stream = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors=errors)
  monkeypatch.setattr(sys, "stdout", stream)
  with printable_names():
    print("caf\udce9")
  assert stream.errors == errors  # put back
  stream.flush()
  assert stream.buffer.getvalue() == printed


def test_frame_folders_in_number_order_without_hidden_files(tmp_path):
  # `frame_2` before `frame_10` (unpadded numbering), and macOS `._*` copies left out
  frames = [np.full((H, W, 3), 20 * i, np.uint8) for i in range(4)]
  for side in ("l", "r"):
    (tmp_path / side).mkdir()
    for i, f in zip((1, 2, 10, 11), frames):
      cv2.imwrite(str(tmp_path / side / f"frame_{i}.png"), f)
    (tmp_path / side / "._frame_1.png").write_bytes(b"\x00\x05\x16\x07")
  lv, rv, names = video_io.load_stereo(tmp_path / "l", tmp_path / "r")
  assert names == ["frame_1", "frame_2", "frame_10", "frame_11"]
  np.testing.assert_array_equal(lv, np.stack(frames))
  lazy, _, lazy_names = video_io.open_stereo(tmp_path / "l", tmp_path / "r")
  assert lazy_names == names
  np.testing.assert_array_equal(lazy[0:4], lv)
  # A link to a missing frame in both views (a link farm into a moved dataset) is named, not
  # a video one frame short.
  for side in ("l", "r"):
    (tmp_path / side / "frame_3.png").symlink_to(tmp_path / "moved" / "frame_3.png")
  with pytest.raises(FileNotFoundError, match=r"frame_3\.png: a symbolic link to a missing "
                     r"file or folder, or a loop of links \(.*moved/frame_3\.png\)"):
    video_io.open_stereo(tmp_path / "l", tmp_path / "r")


def test_matmul_precision_covers_every_window_and_is_recorded(tmp_path, folders, npz_ckpt,
                                                             monkeypatch):
  """`--matmul-precision highest` (full float32 on GPUs, where XLA's default is TF32) is in
  effect while the windows are computed, which happens as the outputs draw them; without
  the flag JAX's own setting stays; summary.json records the precision in effect."""
  import jax  # pylint: disable=import-outside-toplevel
  seen = []

  def recording_model(variables, lw, rw, *, cfg, iters, pads, check_memory, cache, start,
                      keep_from=None):
    seen.append(str(jax.config.jax_default_matmul_precision))
    hp, wp = lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]
    return np.ones((len(lw), hp, wp), np.float32)

  monkeypatch.setattr(inference, "_run_window", recording_model)
  for precision, want in (("highest", "highest"), (None, "None"), ("default", "default")):
    extra = ["--matmul-precision", precision] if precision else []
    out = tmp_path / f"out_{precision}"
    assert _infer(*folders, npz_ckpt, out, "--format", "npy", "--window", "2", "--stride", "1",
                  *extra) == 0
    assert len(seen) >= 2 and set(seen) == {want}, (precision, seen)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["matmul_precision"] == (precision or "default")  # None: JAX's default
    seen.clear()
  assert str(jax.config.jax_default_matmul_precision) == "None"  # put back after the run


# XLA's report of a device out of memory, as a GPU prints it (shortened).
XLA_OUT_OF_MEMORY = """RESOURCE_EXHAUSTED: Out of memory while trying to allocate 41.27GiB.
BufferAssignment OOM Debugging.
BufferAssignment stats:
             parameter allocation:    1.25GiB
              constant allocation:         0B
        maybe_live_out allocation:   70.31MiB
     preallocated temp allocation:   41.27GiB
                 total allocation:   42.59GiB
Peak buffers:
\tBuffer 1:
\t\tSize: 5.27GiB
\t\tOperator: op_name="jit(forward)/update_block/gru/conv"
"""


@pytest.mark.parametrize("raised, rc, message", [
    (MemoryError("Unable to allocate 1.09 TiB for an array"), 2,
     "sav-jax bench: error: out of host memory: Unable to allocate 1.09 TiB"),
    (KeyboardInterrupt(), 130, "sav-jax bench: interrupted"),
    (jax.errors.JaxRuntimeError(XLA_OUT_OF_MEMORY), 2,
     "sav-jax bench: error: out of memory on the device: RESOURCE_EXHAUSTED: Out of memory "
     "while trying to allocate 41.27GiB.; use a smaller --batch")])
def test_memory_errors_and_interrupts_are_one_line(monkeypatch, capsys, raised, rc, message,
                                                   run_command):
  # Frames far beyond the machine's memory (numpy's MemoryError while building the inputs),
  # a device out of memory (XLA's error and its buffer tables) and Ctrl-C gave tracebacks.
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel

  def run(args):
    raise raised

  monkeypatch.setattr(bench, "run", run)
  argv = ["bench", "--height", "100000", "--width", "100000"]
  monkeypatch.setattr("sys.argv", ["sav-jax", *argv])
  assert run_command(lambda: cli.main()) == rc  # (its immediate exit after Ctrl-C as status)
  err = capsys.readouterr().err
  assert err.startswith(message) and err.count("\n") == 1, err
  if rc == 130:  # called from Python with arguments, the caller gets the interrupt
    with pytest.raises(KeyboardInterrupt):
      cli.main(argv)


def test_an_interrupt_while_the_sub_commands_load_is_one_line(monkeypatch, capsys, run_command):
  # Ctrl-C in the first half second (the sub-commands' imports) gave a traceback
  def build_parser():
    raise KeyboardInterrupt

  monkeypatch.setattr(cli, "build_parser", build_parser)
  monkeypatch.setattr("sys.argv", ["sav-jax", "demo"])
  assert run_command(lambda: cli.main()) == 130
  assert capsys.readouterr().err == "sav-jax: interrupted\n"
  with pytest.raises(KeyboardInterrupt):  # called from Python with arguments: the caller's
    cli.main(["demo"])


def test_a_ctrl_c_dropped_while_jax_loads_stops_the_command(monkeypatch, capsys, run_command):
  # Ctrl-C ~1 s after `sav-jax infer` started landed in JAX's GC callback while JAX was being
  # imported, before interrupts were remembered: dropped, the run went on and exited 0
  import contextlib  # pylint: disable=import-outside-toplevel
  import signal  # pylint: disable=import-outside-toplevel

  from sav_jax import _signals  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel

  @contextlib.contextmanager
  def dropped_while_loading():
    try:  # what Python does with a KeyboardInterrupt raised in a GC callback
      signal.getsignal(signal.SIGINT)(signal.SIGINT, None)
    except KeyboardInterrupt:
      pass
    yield

  monkeypatch.setattr(runtime, "preserved_settings", dropped_while_loading)
  monkeypatch.setattr(bench, "run", lambda args: _signals.raise_if_interrupted() or 0)
  monkeypatch.setattr("sys.argv", ["sav-jax", "bench"])
  assert run_command(lambda: cli.main()) == 130  # (raise_if_interrupted: a window's start)
  assert capsys.readouterr().err == "sav-jax bench: interrupted\n"


def test_other_runtime_errors_keep_their_traceback(monkeypatch):
  # Only running out of memory is the user's to fix by a smaller input: XLA's other errors are
  # bugs to report, with their traceback.
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel

  def run(args):
    raise jax.errors.JaxRuntimeError("INTERNAL: Failed to launch kernel")

  monkeypatch.setattr(bench, "run", run)
  with pytest.raises(jax.errors.JaxRuntimeError, match="INTERNAL"):
    cli.main(["bench"])
  assert sav_jax.runtime.out_of_memory(RuntimeError("RESOURCE_EXHAUSTED")) is None  # not XLA's
  long = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: " + "x" * 400)
  assert len(sav_jax.runtime.out_of_memory(long)) == 300


def _positive_model(variables, lw, rw, *, pads, **kwargs):
  """Stand-in for the compiled model: disparity 5 everywhere."""
  return np.full((len(lw), lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]),
                 5.0, np.float32)


def _error_line(capsys):
  """The command's one error line (beside its progress bars)."""
  lines = [l for l in capsys.readouterr().err.splitlines() if "error:" in l]
  assert len(lines) == 1, lines
  return lines[0]


def test_a_full_disk_is_one_error_naming_the_file_and_leaves_no_partial_file(
    tmp_path, npz_ckpt, monkeypatch, capsys):
  # A disk that filled up while the maps were written: numpy's "2048 requested and 992
  # written", naming no file, and a truncated .npy left behind; filling up under the memory
  # map of the disparities killed the process with "Bus error" and no message.
  frames = np.random.default_rng(0).integers(0, 255, (3, 16, 24, 3)).astype(np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  real_save = np.save

  def full_disk_save(path, arr, *a, **k):
    if pathlib.Path(path).stem == "0001":
      pathlib.Path(path).write_bytes(b"\x93NUMPY truncated")
      raise OSError("2048 requested and 992 written")
    return real_save(path, arr, *a, **k)

  monkeypatch.setattr(np, "save", full_disk_save)
  out = tmp_path / "out"
  assert _infer(left, right, npz_ckpt, out, "--format", "npy") == 2
  err = _error_line(capsys)
  assert re.fullmatch(rf"sav-jax infer: error: cannot write {re.escape(str(out))}/disparity/"
                      r"0001\.npy: 2048 requested and 992 written; \d+\.\d MB free on its disk",
                      err), err
  # no 0001 (truncated), and the failed run's other files and provisional summary deleted
  assert not [p for p in out.rglob("*") if p.is_file()], list(out.rglob("*"))
  monkeypatch.setattr(np, "save", real_save)
  # No room for the disparities' temporary file (3 frames of 16 x 24 float32): said before
  # any map is written.
  reserved = []

  def no_room(fd, offset, size):
    reserved.append(size)
    raise OSError(errno.ENOSPC, "No space left on device")

  monkeypatch.setattr(infer.os, "posix_fallocate", no_room)
  assert _infer(left, right, npz_ckpt, tmp_path / "out2", "--format", "npy") == 2
  err = _error_line(capsys)
  assert err.startswith(f"sav-jax infer: error: cannot write the disparities' temporary file in "
                        f"{tmp_path / 'out2'} (0.0 MB): No space left on device; "), err
  assert not (tmp_path / "out2" / "disparity").exists() and reserved == [3 * 16 * 24 * 4]
  monkeypatch.undo()
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  # The video: OpenCV's writer reports no error, and a file without its index ("moov atom
  # not found") was left under the final name, the run reported as a success.
  real_writer = cv2.VideoWriter

  class FillingDisk:  # the first frame reaches the disk, the others do not
    def __init__(self, *args):
      self.writer, self.frames = real_writer(*args), 0

    def isOpened(self):  # pylint: disable=invalid-name
      return self.writer.isOpened()

    def write(self, frame):
      self.frames += 1
      if self.frames == 1:
        self.writer.write(frame)

    def release(self):
      self.writer.release()

  monkeypatch.setattr(viz.cv2, "VideoWriter", FillingDisk)
  assert _infer(left, right, npz_ckpt, tmp_path / "out3", "--format", "npy") == 2
  err = _error_line(capsys)
  assert re.fullmatch(rf"sav-jax infer: error: cannot write {re.escape(str(tmp_path))}/out3/"
                      r"side_by_side\.mp4: the video was not written completely: 3 frames "
                      r"written, the file holds 1 frames \(a full disk\?\); \d+\.\d MB free on "
                      r"its disk", err), err
  assert not (tmp_path / "out3" / "side_by_side.mp4").exists()
  assert not list((tmp_path / "out3").glob(".side_by_side*"))  # nor its temporary file
  assert not [p for p in (tmp_path / "out3").rglob("*") if p.is_file()]  # nor its maps


def test_outputs_of_frames_sharing_a_stem_are_named_by_position_with_a_note(tmp_path, caplog):
  # 0001.png beside 0001.jpg: every output was renamed frame_000000... without a word.
  frame = np.zeros((8, 8, 3), np.uint8)
  for side in ("l", "r"):
    for name in ("0000.png", "0001.png", "0001.jpg"):
      (tmp_path / side).mkdir(exist_ok=True)
      assert cv2.imwrite(str(tmp_path / side / name), frame)
  with caplog.at_level(logging.WARNING):
    _, _, names = video_io.open_stereo(tmp_path / "l", tmp_path / "r")
  assert names == ["frame_000000", "frame_000001", "frame_000002"]
  assert (f"0001.jpg and 0001.png in {tmp_path / 'l'} share a name before the suffix: the "
          "outputs are named by position, frame_000000 to frame_000002") in caplog.text


def test_an_output_subfolder_that_cannot_be_written_fails_before_the_model_runs(
    tmp_path, npz_ckpt, monkeypatch, capsys):
  # A read-only OUT/disparity/ of an earlier run was found only after the model had run
  # ("cannot write PNG"), leaving a provisional summary behind.
  frames = np.zeros((2, 16, 24, 3), np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  out = tmp_path / "out"
  (out / "disparity").mkdir(parents=True)

  def refuse(prefix, dir):  # as a read-only mount answers (root passes any permission bits)
    if pathlib.Path(dir).name == "disparity":
      raise OSError(30, "Read-only file system")
    return real_mkdtemp(prefix=prefix, dir=dir)

  import tempfile  # pylint: disable=import-outside-toplevel
  real_mkdtemp = tempfile.mkdtemp
  monkeypatch.setattr(tempfile, "mkdtemp", refuse)
  monkeypatch.setattr(inference, "_run_window", None)  # must not be reached
  assert _infer(left, right, npz_ckpt, out, "--format", "png16") == 2
  assert _error_line(capsys) == (f"sav-jax infer: error: --out {out / 'disparity'}: cannot "
                                 f"create anything in {out / 'disparity'} (Read-only file system)")
  assert sorted(p.name for p in out.iterdir()) == ["disparity"]  # no summary either


def test_overwrite_into_a_relative_out_and_a_second_run_into_a_busy_out(
    tmp_path, npz_ckpt, monkeypatch, capsys):
  # A relative --out: the files set aside were named relative to it and absolute beside it
  # ("... is not in the subpath of 'o'"), every --overwrite that dropped a format failed.
  # Without --overwrite the second run is refused and changes nothing (only a model test
  # had that).
  # A second run into a folder a run is writing in took its set-aside files for a killed
  # run's and put them back under it: a lock refuses it.
  frames = np.zeros((2, 16, 24, 3), np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  monkeypatch.chdir(tmp_path)
  assert _infer(left, right, npz_ckpt, "o", "--format", "png16,npy") == 0
  kept = _contents(tmp_path / "o")
  capsys.readouterr()
  assert _infer(left, right, npz_ckpt, "o", "--format", "npy") == 2  # (no --overwrite)
  assert _error_line(capsys).endswith("pass --overwrite to replace them")
  assert _contents(tmp_path / "o") == kept
  assert _infer(left, right, npz_ckpt, "o", "--format", "npy", "--overwrite") == 0
  assert sorted(p.name for p in (tmp_path / "o" / "disparity").iterdir()) == [
      "0000.npy", "0001.npy"]
  assert not (tmp_path / "o" / infer.SET_ASIDE).exists()
  capsys.readouterr()
  from sav_jax._locks import FolderLock  # pylint: disable=import-outside-toplevel
  held = FolderLock(tmp_path / "o", infer.LOCK)  # another run's
  try:
    assert _infer(left, right, npz_ckpt, "o", "--format", "npy", "--overwrite") == 2
    assert "is writing into o: wait for it or choose another --out" in _error_line(capsys)
    assert _infer(left, right, npz_ckpt, "new/deeper", "--format", "npy") == 0  # elsewhere: yes
  finally:
    held.release()
  def failing(*args, **kwargs):
    raise ValueError("a frame that no longer decodes")

  monkeypatch.setattr(inference, "_run_window", failing)  # fails: nothing left behind
  capsys.readouterr()
  assert _infer(left, right, npz_ckpt, "new2/deeper", "--format", "npy") == 2
  assert not (tmp_path / "new2").exists()  # nor the folders made for the lock


def test_an_overwrite_run_whose_summary_cannot_be_written_puts_the_earlier_run_back(
    tmp_path, npz_ckpt, monkeypatch, capsys):
  """A full disk as the final summary is written (the last file of a run): the error names
  it, this run's files are deleted and the earlier run's files and summary are put back as
  they were (not two runs' files mixed under a provisional summary)."""
  frames = np.zeros((2, 16, 24, 3), np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  out = tmp_path / "out"
  assert _infer(left, right, npz_ckpt, out, "--format", "npy") == 0
  before = _contents(out)
  real_write = infer.write_text_atomic

  def full_disk(path, text):
    if '"complete": true' in text:  # the final summary, not the provisional one
      raise OSError(errno.ENOSPC, "No space left on device")
    return real_write(path, text)

  monkeypatch.setattr(infer, "write_text_atomic", full_disk)
  capsys.readouterr()
  assert _infer(left, right, npz_ckpt, out, "--format", "pfm", "--overwrite") == 2
  assert _error_line(capsys).startswith(f"sav-jax infer: error: cannot write "
                                        f"{out / 'summary.json'}: No space left on device")
  assert _contents(out) == before


def _mjpg(path, frames, fps=24.0):
  writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps,
                           (frames[0].shape[1], frames[0].shape[0]))
  for frame in frames:
    writer.write(np.ascontiguousarray(frame[..., ::-1]))
  writer.release()
  return path


def test_videos_cut_short_turned_or_at_other_rates_are_named(tmp_path, caplog):
  rng = np.random.default_rng(3)
  frames = [rng.integers(0, 256, (32, 64, 3), dtype=np.uint8) for _ in range(12)]
  full = _mjpg(tmp_path / "right.avi", frames)
  cut = tmp_path / "left.avi"
  cut.write_bytes(full.read_bytes()[:int(full.stat().st_size * 0.6)])  # a partial download
  with pytest.raises(ValueError, match=rf"different frame counts: left has \d+ \({cut}\), right "
                                       rf"has 12 \({full}\); {cut}: \d+ frames decoded where the "
                                       r"file declares 12 \(truncated or corrupt\?"):
    video_io.open_stereo(cut, full)
  turned = _mjpg(tmp_path / "turned.avi", [np.ascontiguousarray(f.transpose(1, 0, 2))
                                           for f in frames])
  with pytest.raises(ValueError, match=r"left is 64x32 .*right is 32x64 .*one is turned: rotation "
                                       "metadata in one video file"):
    video_io.open_stereo(turned, full)
  with pytest.raises(ValueError, match=rf"{tmp_path}: holds video files \(left.avi...\), not "
                                       "frames: pass one video file"):
    video_io.open_stereo(tmp_path, full)
  slow = _mjpg(tmp_path / "slow.avi", frames, fps=15.0)
  with caplog.at_level(logging.WARNING):
    video_io.open_stereo(slow, full)
  assert "the left video runs at 15 frames/s, the right at 24" in caplog.text


def test_progress_bars_are_drawn_on_terminals_only(tmp_path, npz_ckpt, monkeypatch, capsys):
  """In a log file (nohup, a batch job) the bars' carriage-return updates piled up on a line."""
  frames = np.random.default_rng(0).integers(0, 255, (3, 16, 24, 3)).astype(np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  monkeypatch.delitem(sys.modules, "ipykernel", raising=False)  # (not in a notebook)
  assert _infer(left, right, npz_ckpt, tmp_path / "log") == 0  # capsys: no terminal
  err = capsys.readouterr().err
  assert "disparity:" not in err and "video:" not in err and "\r" not in err, err
  monkeypatch.setattr(runtime, "draws_progress", lambda stream=None: True)
  assert _infer(left, right, npz_ckpt, tmp_path / "tty") == 0
  err = capsys.readouterr().err
  assert "disparity: 100%" in err and "video: 100%" in err, err


def test_a_resize_that_turns_the_frames_orientation_is_warned_about(tmp_path, folders, npz_ckpt,
                                                                     caplog, monkeypatch):
  """--resize is HxW; 1280x720 for 1280-wide frames (width x height out of habit) ran the model
  on portrait-distorted frames without a word. A warning naming both sizes, said before the
  checkpoint is read; a size of the frames' orientation (or a square one) is not."""
  def stop(*_, **__):
    raise ValueError("stopped after the size checks")

  monkeypatch.setattr(infer, "load_checkpoint", stop)
  assert H < W  # landscape frames
  cases = (((W, H), True), ((W + 8, H - 1), True), ((2 * H, 2 * W), False), ((40, 40), False),
           ((H, H + 1), False))
  for i, (size, warned) in enumerate(cases):
    caplog.clear()
    with caplog.at_level(logging.WARNING):
      assert _infer(*folders, npz_ckpt, tmp_path / f"out{i}", "--resize", "%dx%d" % size) == 2
    line = (f"--resize {size[0]}x{size[1]} is height x width: it turns the {H}x{W} (height x "
            f"width) frames from landscape to portrait; for their orientation give --resize "
            f"{size[1]}x{size[0]}")
    assert (line in caplog.text) == warned, (size, caplog.text)
    assert ("is height x width" in caplog.text) == warned, (size, caplog.text)
  assert infer.flips_orientation((720, 1280), (1280, 720))
  assert infer.flips_orientation((1280, 720), (720, 1280))
  assert not infer.flips_orientation((720, 1280), (360, 640))
  assert not infer.flips_orientation((720, 720), (1280, 720))


def test_a_demo_out_folder_whose_name_is_not_utf8_is_refused_before_the_run(tmp_path, capsys):
  """Latin-1 bytes (a zip made on Windows): the demo ran the model, then its video writer
  refused the folder (OpenCV's writer cannot take such names)."""
  out = tmp_path / os.fsdecode(b"d\xe9mo")
  assert cli.main(["demo", "--out", str(out), "--frames", "2", "--height", "16", "--width", "32",
                   "--iters", "2", "--no-compile-cache"]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "d\\udce9mo': the --out folder's name is not UTF-8 text" in err
  assert not out.exists()


def test_demo_refuses_an_out_folder_that_is_a_dataset_sequence(tmp_path, capsys, monkeypatch):
  """A folder with left/ and right/ (a `folder` dataset's sequence): the demo's
  disparity/frame_*.png there were read as the sequence's ground truth, as infer's were."""
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(demo, "_weights", lambda args, dtype: 1 / 0)  # (not reached)
  seq = tmp_path / "seq"
  (seq / "left").mkdir(parents=True)
  (seq / "right").mkdir()
  assert cli.main(["demo", "--out", str(seq), "--frames", "2", "--height", "16", "--width", "32",
                   "--iters", "2", "--no-compile-cache"]) == 2
  assert "holds left/ and right/ folders" in capsys.readouterr().err
  assert sorted(p.name for p in seq.iterdir()) == ["left", "right"]


def test_the_held_disparities_are_not_mapped_into_memory(tmp_path, npz_ckpt, monkeypatch):
  """The disparities that wait for the side-by-side video sat in a memory map of their
  temporary file: every frame written stayed in the process's resident memory (1000 frames
  of 240x320: 280 MB more than 40 frames), so the memory grew with the video's length. They
  are written to the file and read back in batches: nothing of it is mapped, and the video
  and its colour range are those of every frame."""
  n = 23
  labels = np.arange(n, dtype=np.uint8) * 11
  frames = np.broadcast_to(labels[:, None, None, None], (n, 8, 12, 3)).copy()
  left = _write_frames(tmp_path / "left", frames)
  right = _write_frames(tmp_path / "right", frames)

  def label_model(variables, lw, rw, *, pads, **kwargs):  # disparity 0.5 (index + 1)
    value = (np.round(lw[:, 0, 0, 0] / 11).astype(np.float32) + 1) / 2
    hp, wp = lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]
    ramp = np.arange(wp, dtype=np.float32) / 16  # a range that differs across columns
    return value[:, None, None] + np.broadcast_to(ramp, (len(lw), hp, wp))

  mapped, shown = [], []
  real_write_video = viz.write_video

  def watching_write_video(path, video, fps=10.0):
    def frames_seen():
      for f in video:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as fh:
          mapped.extend(l for l in fh if str(out) in l)  # (an O_TMPFILE file has no name)
        shown.append(f)
        yield f
    return real_write_video(path, frames_seen(), fps)

  monkeypatch.setattr(inference, "_run_window", label_model)
  monkeypatch.setattr(viz, "write_video", watching_write_video)
  out = tmp_path / "out"
  assert _infer(left, right, npz_ckpt, out, "--format", "npy", "--window", "6",
                "--stride", "4") == 0
  assert not mapped, mapped  # (Linux's view of the process's mappings)
  disp = np.stack([np.load(out / "disparity" / f"{i:04d}.npy") for i in range(n)])
  top, _, lft, _ = pads = inference.pad_amounts(8, 12)
  expected = label_model(None, frames, frames, pads=pads)[:, top:top + 8, lft:lft + 12]
  np.testing.assert_allclose(disp, expected, rtol=1e-6)
  summary = json.loads((out / "summary.json").read_text())
  lo, hi = viz.disparity_range(disp, percentiles=(1.0, 99.0))
  assert summary["video_disparity_range"] == [round(lo, 4), round(hi, 4)]
  assert len(shown) == n  # every frame, each the left view beside its own disparities
  for f, l, d in zip(shown, frames, disp):
    np.testing.assert_array_equal(f, viz.side_by_side(l, viz.colorize(d, lo, hi)))
  assert not list(out.glob(".disparity_*"))


def test_8bit_frames_with_alpha_come_out_rgb(tmp_path):
  """An 8-bit PNG with alpha (BGRA as OpenCV decodes it) takes `to_rgb8`'s path for
  non-contiguous channels (not cv2.cvtColor's): the alpha dropped and the colours in RGB
  order, as the file holds them (a red pixel stays red)."""
  bgra = np.array([[[10, 20, 30, 255], [40, 50, 60, 0], [0, 0, 255, 128]]], np.uint8)
  assert cv2.imwrite(str(tmp_path / "a.png"), bgra)
  notes = set()
  got = video_io.read_frame(tmp_path / "a.png", notes)
  np.testing.assert_array_equal(got, [[[30, 20, 10], [60, 50, 40], [255, 0, 0]]])
  assert [n.split(", e.g.")[0] for n in notes] == ["alpha channel dropped"]


class _FakeCapture:
  """A stand-in for cv2.VideoCapture: `decoded` grey frames 8x8 (level 10 * i), `declared` in
  its header."""

  def __init__(self, decoded, declared):
    self.decoded, self.declared, self.i = decoded, declared, 0

  def isOpened(self):  # pylint: disable=invalid-name
    return True

  def read(self):
    if self.i >= self.decoded:
      return False, None
    self.i += 1
    return True, np.full((8, 8, 3), 10 * (self.i - 1), np.uint8)

  def get(self, prop):
    return {cv2.CAP_PROP_FRAME_COUNT: self.declared, cv2.CAP_PROP_FPS: 25.0}.get(prop, 0.0)

  def release(self):
    pass


def test_a_video_one_frame_short_of_its_header_is_noted(tmp_path, monkeypatch):
  """The note on a video that decodes to fewer frames than its header declares comes from one
  frame missing on (the last one of a cut download), none where the counts agree."""
  video = tmp_path / "v.avi"
  video.write_bytes(b"")
  for decoded, declared, noted in ((3, 4, True), (3, 3, False), (3, 2, False)):
    monkeypatch.setattr(video_io.cv2, "VideoCapture",
                        lambda path, d=decoded, n=declared: _FakeCapture(d, n))
    source = video_io.FrameSource(video)
    assert len(source) == decoded
    want = {f"{video}: 3 frames decoded where the file declares 4 (truncated or corrupt?, or a "
            "variable frame rate, whose count is an estimate)"} if noted else set()
    assert source.notes == want, (decoded, declared)


def test_outputs_are_named_after_the_left_frames(tmp_path):
  """The output names are the --left folder's stems (`left_0001`...), not the right's: the
  disparities are the left view's."""
  frame = np.zeros((8, 8, 3), np.uint8)
  for side in ("left", "right"):
    (tmp_path / side).mkdir()
    for i in (1, 2):
      assert cv2.imwrite(str(tmp_path / side / f"{side}_{i:04d}.png"), frame)
  for read in (video_io.open_stereo, video_io.load_stereo):
    assert read(tmp_path / "left", tmp_path / "right")[2] == ["left_0001", "left_0002"]
    assert read(tmp_path / "right", tmp_path / "left")[2] == ["right_0001", "right_0002"]


def test_videos_at_rates_a_percent_apart_are_noted_and_the_same_source_too(tmp_path, caplog):
  """Frame rates more than 1% apart get the drift note (25 vs 24 frames/s: 4%), rates within
  1% (NTSC's 29.97 beside 30) none; --left and --right naming one source get the note that
  the disparity will be about 0, two sources with the same frames none."""
  frames = [np.full((16, 16, 3), 40 * i, np.uint8) for i in range(3)]
  rates = {"v24": 24.0, "v25": 25.0, "v2997": 30000 / 1001, "v30": 30.0}
  paths = {name: _mjpg(tmp_path / f"{name}.avi", frames, fps) for name, fps in rates.items()}
  for left, right, noted in (("v24", "v25", True), ("v2997", "v30", False)):
    caplog.clear()
    with caplog.at_level(logging.WARNING):
      video_io.open_stereo(paths[left], paths[right])
    assert ("frames are paired by their index, so the views drift apart" in caplog.text) == noted
  folder = _write_frames(tmp_path / "f", np.stack(frames))
  copy = _write_frames(tmp_path / "g", np.stack(frames))
  same = "--left and --right are the same source"
  for read in (video_io.open_stereo, video_io.load_stereo):
    caplog.clear()
    with caplog.at_level(logging.WARNING):
      read(folder, tmp_path / "f" / ".." / "f")
    assert (f"{same} ({os.path.realpath(folder)}): identical views give a disparity of "
            "about 0") in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
      read(folder, copy)
    assert same not in caplog.text


def test_frame_count_mismatch_names_the_first_frame_one_folder_lacks(tmp_path):
  """With several frames missing on the right (2 and 4 of 0-4), the message names the first
  of them; numbers repeated in one folder only (two cameras' files in one folder) make no
  claim about shifted pairs."""
  frame = np.zeros((8, 8, 3), np.uint8)
  for side, numbers in (("l", (0, 1, 2, 3, 4)), ("r", (0, 1, 3))):
    (tmp_path / side).mkdir()
    for i in numbers:
      assert cv2.imwrite(str(tmp_path / side / f"{i:04d}.png"), frame)
  with pytest.raises(ValueError, match=r"left has 5 .*right has 3 .*; e\.g\. frame 2 is in the "
                                       r"left folder \(0002\.png\), not in the right$"):
    video_io.open_stereo(tmp_path / "l", tmp_path / "r")
  with pytest.raises(ValueError, match=r"; e\.g\. frame 2 is in the right folder \(0002\.png\), "
                                       "not in the left$"):
    video_io.load_stereo(tmp_path / "r", tmp_path / "l")  # (the side is named as it is)
  shifted = video_io._shifted_pairing  # pylint: disable=protected-access
  assert shifted(["a_5.png", "b_5.png"], ["5.png", "6.png"]) is None
  assert shifted(["5.png", "6.png"], ["a_5.png", "b_5.png"]) is None


def test_disparities_back_at_the_input_size_scale_by_the_widths_alone():
  """A disparity is a horizontal distance: back at the input size it is scaled by the widths'
  align_corners factor ((W - 1) / (w - 1): 2 for 3 -> 5 columns), whatever the heights'
  (2 -> 5 rows would give 4)."""
  back = video_io.disparities_to_input_size(np.full((1, 2, 3), 1.5, np.float32), 5, 5)
  assert back.shape == (1, 5, 5)
  np.testing.assert_allclose(back, 3.0)
  tall = video_io.disparities_to_input_size(np.ones((1, 9, 2), np.float32), 3, 4)
  np.testing.assert_allclose(tall, 3.0)  # (4 - 1) / (2 - 1), not the heights' 2 / 8


def test_npy_maps_stay_float32_and_map_suffixes_are_read_in_any_case(tmp_path):
  """`.npy` disparities are float32 files (a float16 one rounds 1000.1 to 1000 and 1/3 to
  0.33325); `read_map` takes `F.PNG`, `F.NPY`... as their lower-case suffixes (files from
  Windows tools)."""
  d = np.array([[1 / 3, 1000.1], [0.0, 64.25]], np.float32)
  video_io.write_map(tmp_path / "f.npy", d, "npy")
  raw = np.load(tmp_path / "f.npy")
  assert raw.dtype == np.float32
  np.testing.assert_array_equal(raw, d)
  for fmt in video_io.DISPARITY_FORMATS:
    path = video_io.disparity_path(tmp_path, "g", fmt)
    video_io.write_map(path, d, fmt)
    upper = path.rename(path.with_suffix(path.suffix.upper()))
    # (png16: KITTI's round(256 d) integers, 65535 at most: 1000.1 saturates)
    want = np.minimum(np.round(d * 256), 65535) / 256 if fmt == "png16" else d
    np.testing.assert_array_equal(video_io.read_map(upper), want)


def test_video_files_with_upper_case_suffixes_are_read(tmp_path):
  """Cameras name their videos `IMG_0001.MOV` or `CLIP.AVI`: the suffix is matched in any
  case (was refused as "expected a frame folder or a video file")."""
  frames = [np.full((16, 16, 3), 40 * i, np.uint8) for i in range(3)]
  video = _mjpg(tmp_path / "clip.avi", frames).rename(tmp_path / "CLIP.AVI")
  left, right, names = video_io.open_stereo(video, video)
  assert len(left) == len(right) == 3 and names[0] == "frame_000000"
  assert len(video_io.read_video_file(video)) == 3


def test_infer_argument_parsers_by_hand():
  """--resize takes HxW (or H,W, any case of the x) of positive integers, nothing else;
  --format values are split at commas, lower-cased, de-duplicated in their order (png16 by
  default); --iters >= 2 and 1 <= --stride <= --window <= 32."""
  import argparse  # pylint: disable=import-outside-toplevel

  from sav_jax.tools import UsageError  # pylint: disable=import-outside-toplevel
  for text, want in (("720x1280", (720, 1280)), ("720X1280", (720, 1280)),
                     (" 36,48 ", (36, 48)), ("1x1", (1, 1))):
    assert infer.parse_size(text) == want, text
  for text in ("0x5", "5x0", "-2x5", "720", "720x1280x3", "axb", "720x"):
    with pytest.raises(argparse.ArgumentTypeError, match="expected HEIGHTxWIDTH"):
      infer.parse_size(text)
  assert infer.parse_formats(None) == ["png16"]
  assert infer.parse_formats(["npy, PFM", "npy", "EXR,png16"]) == ["npy", "pfm", "exr", "png16"]
  with pytest.raises(UsageError, match="unknown --format 'tif'"):
    infer.parse_formats(["npy,tif"])
  assert infer.parse_camera_pair("3, 2") == (3, 2) and infer.parse_camera_pair("0,1") == (0, 1)
  for text in ("2,2", "2", "2,4", "1,2,3"):
    with pytest.raises(argparse.ArgumentTypeError, match="two different KITTI camera numbers"):
      infer.parse_camera_pair(text)
  infer.check_model_args(2, 4, 4)
  infer.check_model_args(2, 4, 1)
  infer.check_model_args(2, 32, 10)  # --window: at most 32 (the temporal attention's length)
  for iters, window, stride in ((1, 4, 2), (2, 4, 5), (2, 4, 0), (2, 33, 10)):
    with pytest.raises(UsageError):
      infer.check_model_args(iters, window, stride)


def test_output_paths_name_every_file_of_a_run():
  """The files of a run, by frame name: each disparity format, the video and summary, and with
  a calibration one depth file (its format) and one point cloud per frame."""
  out = pathlib.Path("out")
  calib = infer.Calibration(100.0, 100.0, 10.0, 8.0, 0.5)
  paths = infer.output_paths(out, ["a", "b"], ["png16", "npy"], calib, "exr")
  assert [p.as_posix() for p in paths] == [
      "out/disparity/a.png", "out/disparity/a.npy", "out/disparity/b.png", "out/disparity/b.npy",
      "out/side_by_side.mp4", "out/summary.json", "out/depth/a.exr", "out/depth/b.exr",
      "out/pointclouds/a.ply", "out/pointclouds/b.ply"]
  assert [p.as_posix() for p in infer.output_paths(out, ["a"], ["pfm"], None, "npy")] == [
      "out/disparity/a.pfm", "out/side_by_side.mp4", "out/summary.json"]


def _outputs_written(out: pathlib.Path, d: np.ndarray, formats: list[str]) -> dict:
  """`write_outputs`' summary fields for the disparities `d` [T, H, W] given directly (no
  model, no calibration), with black frames of their size, into the new folder `out`."""
  import argparse  # pylint: disable=import-outside-toplevel
  out.mkdir()
  args = argparse.Namespace(window=len(d), fps=10.0, max_depth=None, depth_format="npy")
  names = [f"{i:04d}" for i in range(len(d))]
  return infer.write_outputs(out, names, np.zeros((*d.shape, 3), np.uint8), [(0, d)], formats,
                             None, args, [])


def test_write_outputs_counts_by_hand_and_colours_the_video_between_percentiles(tmp_path):
  """`write_outputs` on disparities given directly (no model): 3 frames of 2, 4, 6 px but
  one pixel of 24 (the frame width: no pixel can match that far) and one of 1000 (above the
  16-bit PNG's 65535 / 256): 2 disparities at least the width, 1 saturated in the PNG (not
  in the npy written after it), and the video's colours span the 1st to 99th percentile of
  the 1152 values, 2 to 6 px (the outlier is not the top of the range)."""
  d = np.repeat(np.array([2.0, 4.0, 6.0], np.float32), 16 * 24).reshape(3, 16, 24)
  d[2, 0, 0], d[2, 0, 1] = 24.0, 1000.0
  assert _outputs_written(tmp_path / "out", d, ["png16", "npy"]) == {
      "video_disparity_range": [2.0, 6.0], "png16_saturated_pixels": 1,
      "disparities_beyond_width": 2, "empty_point_clouds": 0}


@pytest.mark.parametrize("sample, every, video_range", [(None, 3, [2.0, 50.0]),
                                                       (400, 2, [2.0, 6.0])])
def test_the_video_colour_range_samples_every_step_th_row_and_column_of_every_frame(
    tmp_path, monkeypatch, sample, every, video_range):
  """3 frames of 15 x 24 px (1080 values) whose pixels on every `every`-th row and column hold
  2, 4 and 6 px and all others 50 px. Within RANGE_SAMPLE values every pixel counts: on every
  3rd row and column 11% of them are small, so the 1st to 99th percentile is 2 to 50 px.
  With at most 400 values the step is ceil(sqrt(1080 / 400)) = 2: rows 0, 2, ..., 14 and
  columns 0, 2, ..., 22, exactly the 288 small values on every 2nd row and column, 2 to 6 px
  (a step of 1 or 3 would take pixels of 50 px)."""
  if sample is not None:
    monkeypatch.setattr(infer, "RANGE_SAMPLE", sample)
  d = np.full((3, 15, 24), 50.0, np.float32)
  d[:, ::every, ::every] = np.array([2.0, 4.0, 6.0], np.float32)[:, None, None]
  assert _outputs_written(tmp_path / "out", d, ["npy"])["video_disparity_range"] == video_range


@pytest.mark.parametrize("raised, says", [
    (lambda path: OSError(errno.ENOSPC, "No space left on device"),
     r"cannot write {path} \(3\.0 MB\): No space left on device; \d+\.\d MB free on its disk"),
    # a message that names the file and the disk's free space itself: each said once
    (lambda path: OSError(f"{path}: 2 of 3 frames written; 1.5 MB free on its disk"),
     r"cannot write {path} \(3\.0 MB\): 2 of 3 frames written; 1\.5 MB free on its disk"),
    (lambda path: KeyboardInterrupt(), None),
    (lambda path: FileExistsError(errno.EEXIST, "File exists"), None)])
def test_writing_removes_the_partial_file_of_a_write_that_failed(tmp_path, raised, says):
  """`writing`: a write cut short (a full disk, Ctrl-C) leaves no partial file under the
  output's name (a truncated .npy was left behind), unless `remove=False` (a file written
  whole elsewhere first); a full disk becomes one OSError naming the file, the MB it needs
  and the cause, Ctrl-C and a FileExistsError (not the disk's) pass through as they are."""
  path = tmp_path / "0001.npy"
  for remove in (True, False):
    error = raised(path)
    with pytest.raises(OSError if says else type(error)) as info:
      with infer.writing(path, size=3 << 20, remove=remove):
        path.write_bytes(b"\x93NUMPY truncated")
        raise error
    assert path.exists() is not remove, remove
    if says:
      assert re.fullmatch(says.format(path=re.escape(str(path))), str(info.value)), info.value
      assert info.value.__cause__ is error
    else:
      assert info.value is error
    path.unlink(missing_ok=True)


def test_reserve_takes_the_files_blocks_or_sizes_it_where_the_system_cannot(tmp_path,
                                                                            monkeypatch):
  """`_reserve` allocates the disparities' temporary file (a full disk is found before any
  map is written); a file system without posix_fallocate (ZFS: EINVAL, some FUSE:
  EOPNOTSUPP, ENOSYS) or an OS without it (macOS) gets the file sized instead; any other
  error, a full disk, is raised."""
  size = 3 * 16 * 24 * 4

  def reserved(fallocate=None):
    if fallocate is not None:
      monkeypatch.setattr(os, "posix_fallocate", fallocate)
    with open(tmp_path / "held", "w+b") as f:
      infer._reserve(f, size)  # pylint: disable=protected-access
      return os.fstat(f.fileno())

  assert reserved().st_size == size
  for code in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOSYS, errno.ENOSPC):
    def refuse(fd, offset, length, code=code):
      raise OSError(code, os.strerror(code))

    if code == errno.ENOSPC:
      with pytest.raises(OSError, match="No space left on device"):
        reserved(refuse)
    else:
      assert reserved(refuse).st_size == size, code
  monkeypatch.delattr(os, "posix_fallocate")
  assert reserved().st_size == size


def test_write_outputs_closes_the_windows_generator_when_a_write_fails(tmp_path, monkeypatch):
  """A write that fails closes the windows' generator before the error is raised (its
  progress bar ends its line, not the error's, and its windows are freed), not when the
  error is freed: here while it is still held."""
  import argparse  # pylint: disable=import-outside-toplevel
  monkeypatch.setenv("SAV_IO_THREADS", "1")  # (the error raised at the first frame's submit)
  closed = []

  def windows():
    try:
      for t0 in (0, 3):
        yield t0, np.ones((3, 16, 24), np.float32)
    finally:
      closed.append(t0)

  def full_disk(path, data, fmt):
    raise OSError(errno.ENOSPC, "No space left on device")

  monkeypatch.setattr(video_io, "write_map", full_disk)
  (tmp_path / "out").mkdir()
  args = argparse.Namespace(window=3, fps=10.0, max_depth=None, depth_format="npy")
  with pytest.raises(OSError, match="No space left on device") as info:
    infer.write_outputs(tmp_path / "out", list("abcdef"), np.zeros((6, 16, 24, 3), np.uint8),
                        windows(), ["npy"], None, args, [])
  assert closed == [0], info  # closed in the first window


def test_check_overwrite_refuses_existing_outputs_and_what_is_not_a_file(tmp_path):
  """Existing output files are refused without --overwrite (the first 3 named, the rest
  counted) and taken with it; a folder where an output file goes, or a file where its folder
  goes, is refused even with --overwrite (it would be lost)."""
  out = tmp_path / "out"
  (out / "disparity").mkdir(parents=True)
  paths = [out / "disparity" / f"{i:04d}.npy" for i in range(5)]
  infer.check_overwrite(paths, False, out)  # nothing there yet
  for p in paths:
    p.write_bytes(b"user data")
  with pytest.raises(FileExistsError, match=r"output files exist \(.*0000\.npy, .*0001\.npy, "
                                            r".*0002\.npy and 2 more\); pass --overwrite"):
    infer.check_overwrite(paths, False, out)
  with pytest.raises(FileExistsError, match=r"output files exist \(.*0004\.npy\); pass"):
    infer.check_overwrite(paths[4:], False, out)
  # files no earlier run's summary lists (a user's own, of the outputs' names) are named as such
  with pytest.raises(FileExistsError, match=re.escape(
      f"pass --overwrite to replace them; 5 of them ({paths[0]}, ...) no earlier sav-jax infer "
      f"run in {out} lists as its output: files of your own? --overwrite deletes them too, "
      "another --out keeps them")):
    infer.check_overwrite(paths, False, out, infer.listed_outputs(out))
  (out / "summary.json").write_text(json.dumps({  # an earlier run's: 0003 and 0004 are its
      "tool": "sav-jax infer", "outputs": ["disparity/0003.npy", "disparity/0004.npy"]}))
  with pytest.raises(FileExistsError, match=re.escape(f"; 3 of them ({paths[0]}, ...) no ")):
    infer.check_overwrite([*paths, out / "summary.json"], False, out, infer.listed_outputs(out))
  with pytest.raises(FileExistsError, match=r"0004\.npy, .*summary\.json\); pass --overwrite to "
                                            r"replace them$"):
    infer.check_overwrite([*paths[3:], out / "summary.json"], False, out,
                          infer.listed_outputs(out))
  (out / "summary.json").unlink()
  with pytest.raises(FileExistsError, match=r"0002\.npy and 1 more\); pass"):  # 4: one more
    infer.check_overwrite(paths[:4], False, out)
  infer.check_overwrite(paths, True, out)
  paths[1].unlink()
  paths[1].mkdir()
  for overwrite in (False, True):
    with pytest.raises(FileExistsError, match=r"0001\.npy exists and is not a file"):
      infer.check_overwrite(paths[1:2], overwrite, out)
  (out / "depth").write_text("a file where a folder goes")
  for overwrite in (False, True):
    with pytest.raises(FileExistsError, match=r"depth is a file, not a folder"):
      infer.check_overwrite([out / "depth" / "0000.npy"], overwrite, out)
  assert (out / "depth").read_text() == "a file where a folder goes"


def test_earlier_outputs_takes_only_files_infer_writes_from_its_own_summary(tmp_path):
  """`--overwrite` deletes what an earlier run's summary lists and this run does not write:
  only names infer writes (`disparity|depth/*.png|npy|pfm|exr`, `pointclouds/*.ply`,
  `side_by_side.mp4`), never hidden files, `..` or other folders, and only from a summary of
  `sav-jax infer`'s."""
  out = tmp_path / "out"
  listed = ["disparity/a.png", "disparity/a.npy", "depth/a.exr", "pointclouds/a.ply",
            "side_by_side.mp4", "disparity/.a.npy", "disparity/../keep.npy", "notes.txt",
            "pointclouds/a.npy", "depth/a.ply", "other/a.npy", "disparity/x/a.npy", "summary.json"]
  for rel in listed:
    (out / rel).parent.mkdir(parents=True, exist_ok=True)
    (out / rel).write_bytes(b"x")
  (out / "keep.npy").write_bytes(b"x")
  summary = {"tool": infer.SUMMARY_TOOL, "complete": True, "outputs": listed}
  (out / "summary.json").write_text(json.dumps(summary))
  this_run = [out / "disparity" / "a.png", out / "summary.json"]
  assert sorted(p.relative_to(out.absolute()).as_posix()
                for p in infer.earlier_outputs(out, this_run)) == [
      "depth/a.exr", "disparity/a.npy", "pointclouds/a.ply", "side_by_side.mp4"]
  (out / "summary.json").write_text(json.dumps({**summary, "tool": "python -m eval"}))
  assert infer.earlier_outputs(out, this_run) == []
  assert infer.earlier_outputs(out, this_run) == []


def test_check_not_inputs_keeps_every_output_off_the_inputs(tmp_path):
  """No output replaces an input video, the checkpoint or the calibration file, or goes into
  an input frame folder (beside its frames too: the next run would read it as a frame)."""
  import argparse  # pylint: disable=import-outside-toplevel
  frames = tmp_path / "frames"
  frames.mkdir()
  (frames / "0000.png").write_bytes(b"x")
  video, ckpt, calib = tmp_path / "v.mp4", tmp_path / "w.npz", tmp_path / "calib.txt"
  for path in (video, ckpt, calib):
    path.write_bytes(b"x")
  args = argparse.Namespace(checkpoint=ckpt, calib=calib)
  fine = tmp_path / "out" / "disparity" / "0000.png"
  infer.check_not_inputs([fine], (frames, video), args)
  for path, how, source in ((frames / "0000.png", "replace a file of the input", frames),
                            (frames / "0001.npy", "be written into the input frame folder", frames),
                            (video, "replace the input", video), (ckpt, "replace the input", ckpt),
                            (calib, "replace the input", calib)):
    with pytest.raises(FileExistsError, match=re.escape(f"output {path} would {how} {source}")):
      infer.check_not_inputs([fine, path], (frames, video), args)


def test_out_that_is_a_stereo_folder_sequence_is_refused(tmp_path, capsys):
  """`--out SEQ` beside `SEQ/left` and `SEQ/right` (the `folder` dataset's layout) wrote the
  predictions to `SEQ/disparity/`, which the dataset's reader takes for ground truth: eval
  scored them against themselves (EPE 0). Refused before the weights are read, even with
  --overwrite, and nothing is written."""
  seq = tmp_path / "my_videos" / "test" / "walk"
  frames = np.zeros((2, 8, 8, 3), np.uint8)
  left, right = _write_frames(seq / "left", frames), _write_frames(seq / "right", frames)
  ckpt = tmp_path / "w.npz"
  ckpt.write_bytes(b"never read")
  for extra in ((), ("--overwrite",)):
    assert _infer(left, right, ckpt, seq, *extra) == 2
    err = capsys.readouterr().err
    assert f"--out {seq} holds left/ and right/ folders" in err, err
    assert sorted(p.name for p in seq.iterdir()) == ["left", "right"]
  # a sequence with left/ but no right/ is not one: the run goes on (to the checkpoint here)
  other = tmp_path / "other"
  _write_frames(other / "left", frames)
  assert _infer(left, right, ckpt, other) == 2
  assert "holds left/ and right/" not in capsys.readouterr().err


def test_calibrated_outputs_pair_each_frame_with_its_disparity_colours_and_depth(
    tmp_path, npz_ckpt, monkeypatch):
  """A run with a stand-in model (no compile) whose disparity labels the frame (frame t, grey
  level 40 (t + 1): 2 (t + 1) px): each frame's files hold its own disparity (KITTI's x256 in
  the 16-bit PNG), depth fx * baseline / (d + doffs) in the default npy, and a point cloud
  coloured by its own left frame; the video shows them in order, at the 10 frames/s of frame
  folders."""
  levels = (40, 80, 120)
  frames = np.stack([np.full((16, 24, 3), v, np.uint8) for v in levels])
  left = _write_frames(tmp_path / "l", frames)
  right = _write_frames(tmp_path / "r", frames)

  def label_model(variables, lw, rw, *, cfg, iters, pads, check_memory, cache, start,
                  keep_from=None):
    value = np.round(lw[:, 0, 0, 0] / 20).astype(np.float32)  # 2 (t + 1)
    hp, wp = lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]
    return -np.broadcast_to(value[:, None, None], (len(lw), hp, wp)).copy()

  monkeypatch.setattr(inference, "_run_window", label_model)
  out = tmp_path / "out"
  assert _infer(left, right, npz_ckpt, out, "--format", "png16,npy", "--fx", "100",
                "--baseline", "0.5", "--doffs", "3") == 0  # (one window: one chunk of 3)
  for t, name in enumerate(["0000", "0001", "0002"]):
    d = 2.0 * (t + 1)
    png = cv2.imread(str(out / "disparity" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and (png == 256 * d).all(), (t, np.unique(png))
    np.testing.assert_array_equal(np.load(out / "disparity" / f"{name}.npy"),
                                  np.full((16, 24), d, np.float32))
    depth = np.load(out / "depth" / f"{name}.npy")
    np.testing.assert_allclose(depth, 100 * 0.5 / (d + 3), rtol=1e-6)
    xyz, rgb = viz.read_ply(out / "pointclouds" / f"{name}.ply")
    assert len(xyz) == 16 * 24 and (rgb == levels[t]).all(), (t, np.unique(rgb))
    np.testing.assert_allclose(xyz[:, 2], 100 * 0.5 / (d + 3), rtol=1e-6)
    # x = (u - cx) z / fx, y = (v - cy) z / fx about the frame's centre (cx 11.5, cy 7.5)
    reach = 100 * 0.5 / (d + 3) / 100 * np.array([11.5, 7.5])
    np.testing.assert_allclose([-xyz[:, 0].min(), xyz[:, 0].max(), -xyz[:, 1].min(),
                                xyz[:, 1].max()], np.repeat(reach, 2), rtol=1e-5)
  summary = json.loads((out / "summary.json").read_text())
  assert summary["video_fps"] == 10.0 and summary["frames"] == 3
  # the run as given (defaults: --window 20, --stride 10), the calibration's filled in
  assert {k: summary[k] for k in ("height", "width", "model_size", "iters", "window", "stride",
                                  "formats", "max_depth", "left", "right", "calibration")} == {
      "height": 16, "width": 24, "model_size": [16, 24], "iters": ITERS, "window": 20,
      "stride": 10, "formats": ["png16", "npy"], "max_depth": None, "left": str(left),
      "right": str(right), "calibration": {"fx": 100.0, "fy": 100.0, "cx": 11.5, "cy": 7.5,
                                           "baseline": 0.5, "doffs": 3.0}}
  # its list for a later --overwrite: every file of the run
  assert sorted(summary["outputs"]) == sorted(p.relative_to(out).as_posix()
                                              for p in out.rglob("*") if p.is_file())
  assert sorted(p.name for p in (out / "depth").iterdir()) == ["0000.npy", "0001.npy", "0002.npy"]
  video = video_io.read_video_file(out / "side_by_side.mp4")
  assert video.shape == (3, 16, 48, 3)  # left | colourized disparity, dark to bright: 2, 4, 6 px
  brightness = video[:, :, 24:].astype(np.float32).mean(axis=(1, 2, 3))
  assert brightness[0] < brightness[1] < brightness[2], brightness
  vmin, vmax = summary["video_disparity_range"]
  for t in range(3):  # each frame's own colours, not another's nor the invalid white (mp4: lossy)
    want = viz.colorize(np.full((16, 24), 2.0 * (t + 1), np.float32), vmin, vmax)
    assert np.abs(video[t, :, 24:].astype(np.float32) - want).mean() < 8, t
  assert video_io.video_fps(out / "side_by_side.mp4") == 10.0


def test_an_earlier_runs_list_never_deletes_through_links(tmp_path):
  """The files an earlier run's summary lists are deleted (`--overwrite`'s `earlier_outputs`,
  `put_back` after an unfinished run) only where they are plain files in --out: not through a
  linked subfolder (a user's `depth -> ~/data`) nor a linked file."""
  out, user = tmp_path / "out", tmp_path / "user"
  user.mkdir()
  (user / "a.npy").write_bytes(b"user data")
  (user / "b.npy").write_bytes(b"user data")
  (out / "disparity").mkdir(parents=True)
  (out / "depth").symlink_to(user)
  (out / "disparity" / "a.npy").write_bytes(b"run")
  (out / "disparity" / "b.npy").symlink_to(user / "b.npy")
  listed = ["depth/a.npy", "disparity/a.npy", "disparity/b.npy"]
  summary = {"tool": infer.SUMMARY_TOOL, "complete": True, "outputs": listed}
  (out / "summary.json").write_text(json.dumps(summary))
  assert infer.earlier_outputs(out, []) == [(out / "disparity" / "a.npy").absolute()]
  (out / infer.SET_ASIDE).mkdir()  # an unfinished --overwrite run's
  (out / "summary.json").write_text(json.dumps({**summary, "complete": False}))
  (out / "pointclouds").mkdir()  # made by the unfinished run, left empty: removed
  assert infer.put_back(out) == 0
  assert not (out / "pointclouds").exists()
  assert not (out / "disparity" / "a.npy").exists()  # the unfinished run's own file: deleted
  assert (user / "a.npy").read_bytes() == (user / "b.npy").read_bytes() == b"user data"
  assert (out / "disparity" / "b.npy").is_symlink() and (out / "depth").is_symlink()
  (tmp_path / "empty").mkdir()  # a user's linked folder stays, even empty
  (out / "pointclouds").symlink_to(tmp_path / "empty")
  (out / infer.SET_ASIDE).mkdir()
  assert infer.put_back(out) == 0
  assert (out / "pointclouds").is_symlink() and (tmp_path / "empty").is_dir()


def test_put_back_restores_the_set_aside_files_unless_the_run_is_known_complete(tmp_path):
  """Only a summary saying `"complete": true` lets `put_back` delete the set-aside files of
  the earlier run; one that does not say (`complete` missing or not a boolean) has them put
  back, as for an unfinished run, and the files it lists are kept (only a provisional
  summary, `"complete": false`, is known to list an unfinished run's own files); so does
  another tool's `summary.json`, whatever it says."""
  for complete in ({}, {"complete": None}, {"complete": "yes"},
                   {"tool": "python -m eval", "complete": True},
                   {"tool": "python -m eval", "complete": False}):
    out = tmp_path / str(len(list(tmp_path.iterdir())))
    (out / infer.SET_ASIDE / "disparity").mkdir(parents=True)
    (out / infer.SET_ASIDE / "disparity" / "a.npy").write_bytes(b"earlier run")
    (out / "disparity").mkdir()
    (out / "disparity" / "b.npy").write_bytes(b"kept")
    (out / "summary.json").write_text(json.dumps({"tool": infer.SUMMARY_TOOL, **complete,
                                                  "outputs": ["disparity/b.npy"]}))
    assert infer.put_back(out) == 1, complete
    assert (out / "disparity" / "a.npy").read_bytes() == b"earlier run"
    assert (out / "disparity" / "b.npy").read_bytes() == b"kept"
    assert not (out / infer.SET_ASIDE).exists()


def test_the_output_video_plays_at_the_left_videos_rate(tmp_path, npz_ckpt, monkeypatch):
  """Without --fps, side_by_side.mp4 takes the left input video's frame rate (12.5 here, not
  frame folders' 10), so that it plays at the input's speed; --fps sets it."""
  frames = [np.full((16, 24, 3), 40 * (i + 1), np.uint8) for i in range(3)]
  left = _mjpg(tmp_path / "left.avi", frames, fps=12.5)
  right = _mjpg(tmp_path / "right.avi", frames, fps=12.5)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  for out, extra, fps in (("a", (), 12.5), ("b", ("--fps", "7"), 7.0),
                          ("c", ("--fps", "119.8765"), 119.88)):  # the rate MPEG-4 can time
    assert _infer(left, right, npz_ckpt, tmp_path / out, *extra) == 0
    assert json.loads((tmp_path / out / "summary.json").read_text())["video_fps"] == fps
    assert video_io.video_fps(tmp_path / out / "side_by_side.mp4") == fps
    assert (sorted(p.name for p in (tmp_path / out / "disparity").iterdir())
            == ["frame_000000.png", "frame_000001.png", "frame_000002.png"])


def test_overwrite_never_deletes_input_frames_an_earlier_summary_lists(tmp_path, npz_ckpt,
                                                                       monkeypatch, capsys):
  """An earlier run's summary may list files that are now this run's input (frames copied
  into `out/depth/` and given as --left): `--overwrite` refuses to set them aside for deletion
  before anything runs, and the frames stay; so are input frames where this run's own outputs
  go (`out2/disparity/0000.png`), with no summary at all (a stand-in model: a run that went on
  would replace them)."""
  frames = np.zeros((2, 16, 24, 3), np.uint8)
  out = tmp_path / "out"
  left = _write_frames(out / "depth", frames)
  right = _write_frames(tmp_path / "r", frames)
  (out / "summary.json").write_text(json.dumps({
      "tool": infer.SUMMARY_TOOL, "complete": True,
      "outputs": ["depth/0000.png", "depth/0001.png", "side_by_side.mp4"]}))
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  assert _infer(left, right, npz_ckpt, out, "--overwrite") == 2
  assert "would replace a file of the input" in _error_line(capsys)
  assert sorted(p.name for p in left.iterdir()) == ["0000.png", "0001.png"]
  left = _write_frames(tmp_path / "out2" / "disparity", frames)
  before = {p.name: p.read_bytes() for p in left.iterdir()}
  assert _infer(left, right, npz_ckpt, tmp_path / "out2", "--overwrite") == 2
  assert "output " + str(left / "0000.png") + " would replace a file of the input" in (
      _error_line(capsys))
  assert {p.name: p.read_bytes() for p in left.iterdir()} == before


def test_calibration_files_and_options_edge_cases(tmp_path, caplog):
  """A KITTI file whose right matrix is missing is no calibration (not a crash on P3); an
  explicit fx beside a Middlebury cam0 is kept; a width of two numbers is refused; --calib
  with --fx is refused; a principal point far off the centre in x alone is warned about."""
  import argparse  # pylint: disable=import-outside-toplevel

  from sav_jax.tools import UsageError  # pylint: disable=import-outside-toplevel
  calib = tmp_path / "calib.txt"
  calib.write_text("P2: 100 0 30 0  0 100 19.5 0  0 0 1 0\nP3: 100 0 30\n")
  with pytest.raises(UsageError, match="no calibration found"):
    infer.read_calibration(calib)
  calib.write_text("fx 500\nbaseline 0.1\ncam0=[400 0 10; 0 400 8; 0 0 1]\ndoffs 0\n")
  assert infer.read_calibration(calib)["fx"] == 500
  # a key given twice: the last value was taken silently; the same value twice is one
  calib.write_text("fx 500\nbaseline 0.1\nfx: 450  # the old value\nbaseline 0.1\n")
  with pytest.raises(UsageError, match=r"calib\.txt, lines 1 and 3: fx is given twice, with "
                                       "different values; keep one"):
    infer.read_calibration(calib)
  calib.write_text("fx 500\nbaseline 0.1\nbaseline = 0.1\n")
  assert infer.read_calibration(calib) == {"fx": 500, "baseline": 0.1}
  calib.write_text("fx 500\nbaseline 0.1\nwidth 24 16\n")  # the size is one number a line too
  with pytest.raises(UsageError, match="line 3: width must be one number"):
    infer.read_calibration(calib)
  args = argparse.Namespace(calib=calib, fx=500.0, fy=None, cx=None, cy=None, baseline=None,
                            doffs=None, calib_cameras=None)
  with pytest.raises(UsageError, match="give either --calib or --fx"):
    infer.calibration_from_args(args)
  with caplog.at_level(logging.WARNING, "sav_jax.tools.infer"):
    infer.CalibrationSpec(100.0, 0.5, cx=69.5, cy=15.5).resolve(100, 32)  # x: 20%, as lenses
    assert not caplog.text
    infer.CalibrationSpec(100.0, 0.5, cx=90.0, cy=15.5).resolve(100, 32)  # x: 40% off centre
  assert "principal point (cx 90, cy 15.5) is 40% of the frame from the centre" in caplog.text


def test_max_frames_cuts_the_output_names_and_a_video_source_keeping_no_frame_reads(tmp_path):
  """--max-frames 2 of 3 frames names two outputs (names beyond it listed files that were
  never written); output names keep the file stems' case; a video source with keep=0 still
  returns every frame it is asked for."""
  frames = np.stack([np.full((8, 8, 3), 40 * (i + 1), np.uint8) for i in range(3)])
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  for read in (video_io.open_stereo, video_io.load_stereo):
    lv, _, names = read(left, right, max_frames=2)
    assert names == ["0000", "0001"] and len(lv) == 2
  (tmp_path / "m").mkdir()  # names keep their case (`Cam_0001`, not `cam_0001`)
  for i in (1, 2):
    assert cv2.imwrite(str(tmp_path / "m" / f"Cam_{i:04d}.PNG"), frames[i])
  assert video_io.FrameSource(tmp_path / "m").names == ["Cam_0001", "Cam_0002"]
  video = _mjpg(tmp_path / "v.avi", list(frames))
  source = video_io.FrameSource(video, keep=0)
  got = source[0:3]
  assert got.shape == (3, 8, 8, 3)
  assert [abs(int(f.mean()) - 40 * (i + 1)) < 6 for i, f in enumerate(got)] == [True] * 3
  np.testing.assert_array_equal(source[1], got[1])


def test_max_depth_leaves_far_points_out_of_the_point_clouds(tmp_path, npz_ckpt, monkeypatch,
                                                             capsys):
  """With a stand-in disparity of 5 px, fx 100 and baseline 0.5 every point is 10 deep:
  --max-depth 20 keeps all 16 x 24 of each frame, --max-depth 5 none (empty clouds, counted
  in the summary and warned about)."""
  frames = np.zeros((2, 16, 24, 3), np.uint8)
  left, right = _write_frames(tmp_path / "l", frames), _write_frames(tmp_path / "r", frames)
  monkeypatch.setattr(inference, "_run_window", _positive_model)
  for max_depth, points in (("20", 16 * 24), ("5", 0)):
    out = tmp_path / max_depth
    assert _infer(left, right, npz_ckpt, out, "--fx", "100", "--baseline", "0.5",
                  "--max-depth", max_depth) == 0
    for name in ("0000", "0001"):
      xyz, _ = viz.read_ply(out / "pointclouds" / f"{name}.ply")
      assert len(xyz) == points and (xyz[:, 2] == pytest.approx(10.0) if points else True)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["empty_point_clouds"] == (2 if points == 0 else 0)
    assert summary["max_depth"] == float(max_depth)
  assert "2 of the 2 point clouds have no point" in capsys.readouterr().out


def test_demo_refuses_a_negative_seed_by_its_flag_before_the_weights(tmp_path, capsys,
                                                                     monkeypatch):
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(demo, "_weights", lambda *a: pytest.fail("weights built"))
  assert cli.main(["demo", "--out", str(tmp_path / "d"), "--seed", "-1",
                   "--no-compile-cache"]) == 2
  assert "--seed must be >= 0, got -1" in capsys.readouterr().err
  assert not (tmp_path / "d").exists()
