"""`sav-jax infer`'s threads (decoding, writing): the same files in the same places as one
thread writes them, errors raised in the main thread, Ctrl-C stops cleanly."""

import json
import os
import random
import threading
import time

import cv2
import numpy as np
import pytest

from sav_jax import cli, inference, viz
from sav_jax.tools import parallel, video_io

N, H, W = 37, 16, 24


@pytest.fixture(scope="module")
def video(module_tmp_path):
  """Frames whose pixel (0, 0) labels them (i * 6); the rest random (distinct files)."""
  rng = np.random.default_rng(0)
  frames = rng.integers(0, 255, (N, H, W, 3), np.uint8)
  frames[:, 0, 0, :] = (np.arange(N) * 6)[:, None]
  for side in ("left", "right"):
    (module_tmp_path / side).mkdir()
    for i, f in enumerate(frames):
      assert cv2.imwrite(str(module_tmp_path / side / f"{i:04d}.png"), f[..., ::-1])
  return module_tmp_path / "left", module_tmp_path / "right", frames


def label_model(variables, lw, rw, *, cfg, iters, pads, check_memory, cache, start,
                keep_from=None):
  """Frame i's disparity: 1.5 + i / 4 + a per-pixel ramp (from its label pixel)."""
  del variables, rw, cfg, iters, check_memory, cache, start, keep_from
  index = np.round(lw[:, 0, 0, 0] / 6).astype(np.float32)
  hp, wp = lw.shape[1] + pads[0] + pads[1], lw.shape[2] + pads[2] + pads[3]
  ramp = np.linspace(0, 3, hp * wp, dtype=np.float32).reshape(hp, wp)
  return -(1.5 + index[:, None, None] / 4 + ramp)


def _run(video, ckpt, out, *extra):
  left, right, _ = video
  return cli.main(["infer", "--left", str(left), "--right", str(right), "--checkpoint",
                   str(ckpt), "--out", str(out), "--iters", "2", "--format", "png16,npy,pfm",
                   "--fx", "10", "--baseline", "1", *extra])


def _files(out):
  return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
          if p.is_file() and p.name != "summary.json"}


def _summary(out):
  s = json.loads((out / "summary.json").read_text())
  for k in ("seconds", "frames_per_second", "frames_per_second_without_compile",
            "compile_seconds", "left", "right"):
    s.pop(k)
  return s


def test_threads_write_every_frame_in_its_place_as_one_thread_does(tmp_path, video, npz_ckpt,
                                                                   monkeypatch):
  monkeypatch.setattr(inference, "_run_window", label_model)
  monkeypatch.setenv("SAV_IO_THREADS", "1")
  assert _run(video, npz_ckpt, tmp_path / "one") == 0
  # Writers that finish out of order (random delays): still each frame's file at its name.
  real_write_map, real_read_frame = video_io.write_map, video_io.read_frame
  rng = random.Random(0)

  def slow_write_map(path, data, fmt):
    time.sleep(rng.random() * 0.01)
    return real_write_map(path, data, fmt)

  def slow_read_frame(path, notes):
    time.sleep(rng.random() * 0.005)
    return real_read_frame(path, notes)

  monkeypatch.setattr(video_io, "write_map", slow_write_map)
  monkeypatch.setattr(video_io, "read_frame", slow_read_frame)
  monkeypatch.setenv("SAV_IO_THREADS", "4")
  assert _run(video, npz_ckpt, tmp_path / "four") == 0
  one, four = _files(tmp_path / "one"), _files(tmp_path / "four")
  assert one.keys() == four.keys()
  assert len([k for k in one if k.startswith("disparity/")]) == 3 * N
  assert [k for k in one if one[k] != four[k]] == []  # byte for byte, the video included
  assert _summary(tmp_path / "one") == _summary(tmp_path / "four")
  ramp = np.linspace(0, 3, 32 * 32, dtype=np.float32).reshape(32, 32)[8:24, 4:28]
  for i in range(N):  # each frame's own values (none dropped, none swapped)
    want = 1.5 + np.float32(i / 4) + ramp
    np.testing.assert_array_equal(np.load(tmp_path / "four" / "disparity" / f"{i:04d}.npy"),
                                  np.abs(-want))
    np.testing.assert_array_equal(viz.read_pfm(tmp_path / "four" / "disparity" / f"{i:04d}.pfm"),
                                  np.abs(-want))
    _, rgb = viz.read_ply(tmp_path / "four" / "pointclouds" / f"{i:04d}.ply")
    assert rgb[0, 0] == i * 6  # frame i's colours
  assert len(video_io.read_video_file(tmp_path / "four" / "side_by_side.mp4")) == N


def test_an_error_in_a_writer_thread_stops_the_run_and_leaves_nothing(tmp_path, video,
                                                                      npz_ckpt, monkeypatch,
                                                                      capsys):
  monkeypatch.setattr(inference, "_run_window", label_model)
  monkeypatch.setenv("SAV_IO_THREADS", "4")
  real = video_io.write_map

  def failing_write_map(path, data, fmt):
    if path.name == "0017.npy":
      raise OSError(28, "No space left on device")
    return real(path, data, fmt)

  monkeypatch.setattr(video_io, "write_map", failing_write_map)
  out = tmp_path / "out"
  assert _run(video, npz_ckpt, out) == 2
  err = capsys.readouterr().err
  assert f"cannot write {out / 'disparity' / '0017.npy'}: No space left on device" in err
  assert not [p for p in out.rglob("*") if p.is_file()], list(out.rglob("*"))


def test_ctrl_c_stops_the_writers_and_leaves_no_output(tmp_path, video, npz_ckpt,
                                                       monkeypatch):
  monkeypatch.setenv("SAV_IO_THREADS", "4")

  def interrupted(variables, lw, rw, *, start, **kwargs):
    if start > 0:
      raise KeyboardInterrupt
    return label_model(variables, lw, rw, start=start, **kwargs)

  monkeypatch.setattr(inference, "_run_window", interrupted)
  out = tmp_path / "out"
  before = set(threading.enumerate())
  with pytest.raises(KeyboardInterrupt):
    _run(video, npz_ckpt, out)
  assert not [p for p in out.rglob("*") if p.is_file()], list(out.rglob("*"))
  assert not [t for t in set(threading.enumerate()) - before  # (prefetch threads stay, idle)
              if t.name.startswith(("sav-io", "sav-write"))]


def test_ordered_map_and_writer_keep_order_bound_the_work_and_raise_errors():
  rng = random.Random(1)

  def slow(i):
    time.sleep(rng.random() * 0.003)
    return i

  assert list(parallel.ordered_map(slow, range(50), threads=4)) == list(range(50))
  running, most = [0], [0]
  lock = threading.Lock()

  def task(i):
    with lock:
      running[0] += 1
      most[0] = max(most[0], running[0])
    time.sleep(0.002)
    with lock:
      running[0] -= 1
    if i == 30:
      raise ValueError("frame 30")
    return i

  got = []
  with pytest.raises(ValueError, match="frame 30"):
    with parallel.Writer(got.append, ahead=5, threads=3) as w:
      for i in range(60):
        w.submit(task, i)
  assert got[:25] == list(range(25)) and got == sorted(got) and most[0] <= 3
  assert [t for t in threading.enumerate() if t.name.startswith("sav-write")] == []
  with pytest.raises(ValueError, match="frame 30"):
    list(parallel.ordered_map(task, range(60), threads=3))


@pytest.mark.parametrize("value", ["abc", "0"])
def test_a_bad_sav_io_threads_is_named_before_the_model_runs(tmp_path, video, npz_ckpt,
                                                             monkeypatch, capsys, value):
  # (a video file's frames are not decoded in threads: it was found after the first window)
  left, right = tmp_path / "l.mp4", tmp_path / "r.mp4"
  for path in (left, right):
    viz.write_video(path, list(video[2][:4]), fps=10)
  ran = []
  monkeypatch.setattr(inference, "_run_window", lambda *a, **k: ran.append(1) or 1 / 0)
  monkeypatch.setenv("SAV_IO_THREADS", value)
  out = tmp_path / "out"
  assert cli.main(["infer", "--left", str(left), "--right", str(right), "--checkpoint",
                   str(npz_ckpt), "--out", str(out), "--iters", "2"]) == 2
  assert f"SAV_IO_THREADS must be a positive integer, got {value!r}" in capsys.readouterr().err
  assert not ran and not out.exists()


def test_writer_raises_the_first_error_in_submission_order():
  # (a later task that fails first: the error was the later one's, not one thread's)
  def task(i):
    if i == 3:
      time.sleep(0.3)
      raise ValueError("frame 3")
    if i == 5:
      raise ValueError("frame 5")
    return i

  got = []
  with pytest.raises(ValueError, match="frame 3"):
    with parallel.Writer(got.append, ahead=8, threads=4) as w:
      for i in range(20):
        w.submit(task, i)
        time.sleep(0.02)
  assert got == [0, 1, 2]


def test_ctrl_c_while_the_video_is_written_ends_its_threads(tmp_path, video, npz_ckpt,
                                                             monkeypatch):
  # (the colouring threads stayed until the KeyboardInterrupt was freed: past the clean-up)
  monkeypatch.setattr(inference, "_run_window", label_model)
  monkeypatch.setenv("SAV_IO_THREADS", "4")
  real = viz.write_video

  def interrupted(path, frames, fps):
    def some():
      for i, f in enumerate(frames):
        if i == 5:
          raise KeyboardInterrupt
        yield f
    return real(path, some(), fps)

  monkeypatch.setattr(viz, "write_video", interrupted)
  out = tmp_path / "out"
  before, left = set(threading.enumerate()), None
  try:
    _run(video, npz_ckpt, out)
  except KeyboardInterrupt:  # (while it propagates: as the caller's clean-up runs)
    left = [t for t in set(threading.enumerate()) - before
            if t.name.startswith(("sav-io", "sav-write"))]
  assert left == []
  assert not [p for p in out.rglob("*") if p.is_file()], list(out.rglob("*"))


def test_a_bad_frame_found_while_checking_a_folder_ends_the_decoding_threads(tmp_path,
                                                                             monkeypatch):
  # (the threads decoding the frames after it ran on until the ValueError was freed)
  monkeypatch.setenv("SAV_IO_THREADS", "4")
  for i in range(30):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"),
                       np.zeros((8 if i == 2 else 6, 10, 3), np.uint8))
  real = video_io.read_frame
  monkeypatch.setattr(video_io, "read_frame",
                      lambda path, notes: (time.sleep(0.05), real(path, notes))[1])
  before, left = set(threading.enumerate()), None
  try:
    video_io.FrameSource(tmp_path)
  except ValueError as e:
    assert "0002.png is 8x10 but the first frame 0000.png is 6x10" in str(e)
    left = [t for t in set(threading.enumerate()) - before if t.name.startswith("sav-io")]
  assert left == []


def test_a_note_names_the_first_frame_of_its_kind_as_one_thread_does(tmp_path, monkeypatch):
  # (the frame decoded first was named: 0001.png when 0000.png took longer)
  monkeypatch.setenv("SAV_IO_THREADS", "4")
  for i in range(12):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.zeros((6, 10), np.uint8))
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  real = frame_io.decode_image_file

  def slow_first(path):
    time.sleep(0.2 if path.name == "0000.png" else 0)
    return real(path)

  monkeypatch.setattr(frame_io, "decode_image_file", slow_first)
  assert video_io.FrameSource(tmp_path).notes == {
      f"grayscale frames converted to RGB (grey repeated in 3 channels), e.g. "
      f"{tmp_path / '0000.png'}"}


@pytest.mark.parametrize("threads", ["1", "3"])
def test_a_read_inside_the_last_one_decodes_no_frame_again(tmp_path, monkeypatch, threads):
  # (infer's calibrated frames of a chunk, read between windows: the frames after the chunk
  # were dropped, and decoded again for the next window)
  monkeypatch.setenv("SAV_IO_THREADS", threads)
  for i in range(16):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.full((6, 10, 3), i, np.uint8))
  source = video_io.FrameSource(tmp_path)
  decoded = []
  real = video_io.read_frame
  monkeypatch.setattr(video_io, "read_frame",
                      lambda path, notes: decoded.append(path.name) or real(path, notes))
  for a, b in ((0, 8), (2, 6), (4, 12), (6, 10), (8, 16)):
    assert source[a:b][:, 0, 0, 0].tolist() == list(range(a, b))
  assert sorted(decoded) == [f"{i:04d}.png" for i in range(16)]


def test_no_frame_is_decoded_ahead_after_a_run_that_failed(tmp_path, video, npz_ckpt,
                                                            monkeypatch):
  # (the next window's frames queued for decoding ran on after infer had returned)
  running = []
  monkeypatch.setattr(inference, "_run_window",
                      lambda *a, **k: running.append(1) or label_model(*a, **k))
  monkeypatch.setenv("SAV_IO_THREADS", "2")
  real_read, real_write = video_io.read_frame, video_io.write_map
  decoded = []

  def slow_read_frame(path, notes):
    time.sleep(0.05 if running else 0)  # (once the frames are checked)
    decoded.append(path)
    return real_read(path, notes)

  def failing_write_map(path, data, fmt):
    if path.name == "0003.npy":
      raise OSError(28, "No space left on device")
    return real_write(path, data, fmt)

  monkeypatch.setattr(video_io, "read_frame", slow_read_frame)
  monkeypatch.setattr(video_io, "write_map", failing_write_map)
  assert _run(video, npz_ckpt, tmp_path / "out") == 2
  count = len(decoded)
  time.sleep(0.5)
  assert len(decoded) == count


@pytest.mark.parametrize("threads", ["1", "3"])
def test_a_folder_source_read_from_several_threads_gives_each_its_frames(tmp_path,
                                                                         monkeypatch, threads):
  # (the kept frames, shared since the read-ahead came in: KeyError; a folder's reads kept
  # nothing before)
  monkeypatch.setenv("SAV_IO_THREADS", threads)
  for i in range(40):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.full((6, 10, 3), i, np.uint8))
  source = video_io.FrameSource(tmp_path, keep=4)
  wrong = []

  def reads(seed):
    rng = random.Random(seed)
    for _ in range(200):
      a = rng.randrange(36)
      b = a + rng.randrange(1, 5)
      try:
        if source[a:b][:, 0, 0, 0].tolist() != list(range(a, b)):
          wrong.append((a, b))
      except Exception as e:  # pylint: disable=broad-except
        wrong.append(repr(e))

  workers = [threading.Thread(target=reads, args=(seed,)) for seed in range(4)]
  for t in workers:
    t.start()
  for t in workers:
    t.join()
  assert wrong == []


def test_io_threads_default_to_the_cores_up_to_eight(monkeypatch):
  monkeypatch.delenv("SAV_IO_THREADS", raising=False)
  for cores, want in ((None, 1), (1, 1), (2, 2), (6, 6), (64, 8)):
    monkeypatch.setattr(parallel.os, "cpu_count", lambda cores=cores: cores)
    assert parallel.io_threads() == want, cores
  monkeypatch.setenv("SAV_IO_THREADS", "")  # (set but empty: as unset)
  assert parallel.io_threads() == 8
  monkeypatch.setenv("SAV_IO_THREADS", "12")  # (the variable: more than 8 if asked)
  assert parallel.io_threads() == 12


def test_one_io_thread_does_all_the_work_in_the_calling_thread(tmp_path, monkeypatch):
  # (SAV_IO_THREADS=1: no thread decodes ahead, none decodes or writes; results still
  # collected, the folder's frames still read in order)
  monkeypatch.setenv("SAV_IO_THREADS", "1")
  caller = threading.current_thread()
  threads = []

  def where(i):
    threads.append(threading.current_thread())
    return i

  assert parallel.prefetch_pool() is None
  assert list(parallel.ordered_map(where, range(5))) == list(range(5))
  got = []
  with parallel.Writer(got.append) as w:
    for i in range(5):
      w.submit(where, i)
  assert got == list(range(5))
  for i in range(6):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.full((6, 10, 3), i, np.uint8))
  real = video_io.read_frame
  monkeypatch.setattr(video_io, "read_frame",
                      lambda path, notes: where(0) or real(path, notes))
  source = video_io.FrameSource(tmp_path)
  assert source[0:3][:, 0, 0, 0].tolist() == [0, 1, 2]
  assert source[3:6][:, 0, 0, 0].tolist() == [3, 4, 5]
  assert len(threads) == 5 + 5 + 6 + 6 and set(threads) == {caller}


def test_the_decoding_ahead_threads_are_made_once(monkeypatch):
  # (a pool per read: threads that never end, 8 more for every window)
  monkeypatch.setenv("SAV_IO_THREADS", "3")
  pool = parallel.prefetch_pool()
  assert pool is not None and parallel.prefetch_pool() is pool


def test_a_folders_next_frames_are_decoded_ahead_in_the_background(tmp_path, monkeypatch):
  # (while the model runs on this window: the next window's frames are already decoded)
  monkeypatch.setenv("SAV_IO_THREADS", "3")
  for i in range(12):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.full((6, 10, 3), i, np.uint8))
  source = video_io.FrameSource(tmp_path, keep=0)
  decoded = {}
  real = video_io.read_frame

  def read(path, notes):
    decoded[path.name] = threading.current_thread().name
    return real(path, notes)

  monkeypatch.setattr(video_io, "read_frame", read)
  assert source[0:4][:, 0, 0, 0].tolist() == [0, 1, 2, 3]
  deadline = time.monotonic() + 5
  while len(decoded) < 8 and time.monotonic() < deadline:
    time.sleep(0.01)
  ahead = {f"{i:04d}.png" for i in range(4, 8)}
  assert ahead <= decoded.keys() and all(decoded[n].startswith("sav-prefetch") for n in ahead)
  assert "0008.png" not in decoded  # (a window's frames ahead, not more)
  decoded.clear()
  assert source[4:8][:, 0, 0, 0].tolist() == [4, 5, 6, 7]  # served from them
  assert not ahead & decoded.keys()


def test_ordered_map_takes_items_as_the_results_are_taken(monkeypatch):
  # (memory bounded: at most `ahead` results computed beyond the one yielded; and closing
  # it runs no task that had not begun)
  taken, called = [], []

  def items():
    for i in range(100):
      taken.append(i)
      yield i

  def fn(i):
    called.append(i)
    time.sleep(0 if i == 0 else 0.1)
    return i

  results = parallel.ordered_map(fn, items(), ahead=3, threads=2)
  assert next(results) == 0
  assert len(taken) <= 4  # (the one yielded and 3 ahead)
  results.close()
  assert set(called) <= {0, 1, 2}, called


def test_writer_holds_at_most_ahead_unfinished_tasks():
  got = []
  with parallel.Writer(got.append, ahead=3, threads=2) as w:
    for i in range(10):
      w.submit(time.sleep, 0.005)
      assert len(got) >= i + 1 - 3, (i, len(got))
  assert len(got) == 10


def test_writer_raises_a_failed_tasks_error_at_the_next_submit():
  # (not only when it is due: a run went on computing windows after a write had failed)
  def fail():
    raise OSError(28, "No space left on device")

  with pytest.raises(OSError, match="No space left"):
    with parallel.Writer(ahead=100, threads=2) as w:
      w.submit(fail)
      deadline = time.monotonic() + 5
      pending = w._pending  # pylint: disable=protected-access
      while not pending[0].done() and time.monotonic() < deadline:
        time.sleep(0.01)
      w.submit(time.sleep, 0)
      raise AssertionError("the next submit did not raise the error")


def test_an_error_in_the_writers_block_runs_no_task_that_had_not_begun():
  # (Ctrl-C: the frames queued to be written are dropped, not written after it)
  called = []

  def task(i):
    called.append(i)
    time.sleep(0.1)

  with pytest.raises(KeyboardInterrupt):
    with parallel.Writer(ahead=10, threads=2) as w:
      for i in range(8):
        w.submit(task, i)
      raise KeyboardInterrupt
  count = len(called)
  time.sleep(0.15)
  assert count <= 2 and len(called) == count, called


def test_closing_a_folder_source_drops_the_frames_queued_to_be_decoded_ahead(tmp_path,
                                                                            monkeypatch):
  # (infer's error or Ctrl-C: its exit waited for the next window's frames to be decoded)
  monkeypatch.setenv("SAV_IO_THREADS", "2")
  for i in range(32):
    assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), np.full((6, 10, 3), i, np.uint8))
  source = video_io.FrameSource(tmp_path, keep=0)
  begun, decoded = [], []
  real = video_io.read_frame

  def read(path, notes):
    if int(path.stem) >= 16:
      begun.append(path.name)
      time.sleep(0.1)
      decoded.append(path.name)
    return real(path, notes)

  monkeypatch.setattr(video_io, "read_frame", read)
  assert source[0:16][:, 0, 0, 0].tolist() == list(range(16))  # (16..31 queued)
  deadline = time.monotonic() + 5
  while not begun and time.monotonic() < deadline:
    time.sleep(0.005)
  source.close()  # (waits for the decodings begun)
  count = len(decoded)
  time.sleep(0.3)
  workers = parallel.prefetch_pool()._max_workers  # pylint: disable=protected-access
  assert count == len(decoded) <= workers < 16, (count, decoded)


def test_a_frames_disparities_are_written_whole_when_the_system_writes_part(tmp_path,
                                                                            monkeypatch):
  # (pwrite may write less than asked: the rest goes after it; writing nothing is an error,
  # not a loop without end)
  from sav_jax.tools import infer  # pylint: disable=import-outside-toplevel
  path = tmp_path / "held"
  path.write_bytes(bytes(16))
  real = os.pwrite
  monkeypatch.setattr(os, "pwrite", lambda fd, data, offset: real(fd, data[:3], offset))
  with open(path, "r+b") as f:
    infer._pwrite_all(f.fileno(), memoryview(b"abcdefgh"), 4)  # pylint: disable=protected-access
  assert path.read_bytes() == bytes(4) + b"abcdefgh" + bytes(4)
  calls = []

  def nothing(fd, data, offset):
    calls.append(offset)
    assert len(calls) < 100, "pwrite called again and again"
    return 0

  monkeypatch.setattr(os, "pwrite", nothing)
  with open(path, "r+b") as f, pytest.raises(OSError, match="wrote nothing"):
    infer._pwrite_all(f.fileno(), memoryview(b"abc"), 0)  # pylint: disable=protected-access


@pytest.mark.parametrize("threads,window,ahead", [("2", 8, 8), ("6", 4, 12)])
def test_the_writer_holds_a_windows_frames_but_two_per_thread_at_least(tmp_path, video, npz_ckpt,
                                                                       monkeypatch, threads,
                                                                       window, ahead):
  # (memory bounded: the frames given to the writer and not yet written; without the bound a
  # model faster than the disk piled up the whole video's disparities)
  monkeypatch.setattr(inference, "_run_window", label_model)
  monkeypatch.setenv("SAV_IO_THREADS", threads)
  aheads = []

  class Writer(parallel.Writer):
    def __init__(self, *args, **kwargs):
      super().__init__(*args, **kwargs)
      aheads.append(self.ahead)

  monkeypatch.setattr(parallel, "Writer", Writer)
  assert _run(video, npz_ckpt, tmp_path / "out", "--window", str(window), "--stride",
              str(window // 2)) == 0
  assert aheads == [ahead]  # (frames of 1.5 kB: far below 128 MB a window)
