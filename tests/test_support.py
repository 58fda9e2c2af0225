"""The small shared modules the commands rely on: whole-or-nothing text files
(`sav_jax._files`), folder locks (`sav_jax._locks`), Ctrl-C handling (`sav_jax._signals`)
and argument checks (`sav_jax._checks`)."""

import gc
import os
import pathlib
import shutil
import signal
import socket
import threading

import numpy as np
import pytest

from sav_jax import _checks, _files, _locks, _signals, metrics, viz
from tests.conftest import drop_ctrl_c_in_gc

HOLDER = f"{socket.gethostname()} {os.getpid()}"


# ---------------------------------------------------------------- _files
def test_an_atomic_write_replaces_the_file_whole(tmp_path):
  path = tmp_path / "summary.json"
  path.write_text("old, and longer than the new text")
  _files.write_text_atomic(path, "new \u00e9")
  assert path.read_bytes() == "new \u00e9".encode()
  assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_a_failed_atomic_write_keeps_the_old_file_and_no_temporary_one(tmp_path, monkeypatch):
  path = tmp_path / "summary.json"
  path.write_text("the earlier run's")
  with pytest.raises(UnicodeEncodeError):  # fails half-way through writing
    _files.write_text_atomic(path, "ok so far \ud800")
  assert path.read_text() == "the earlier run's"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
  # the rename fails (a full disk, a folder in the way): the temporary file beside the
  # target, .NAME.tmp, is removed again
  renamed = []

  def refuse(src, dst):
    renamed.append(pathlib.Path(src))
    raise OSError(28, "No space left on device")

  monkeypatch.setattr(_files.os, "replace", refuse)
  with pytest.raises(OSError, match="No space left"):
    _files.write_text_atomic(path, "new")
  assert renamed == [tmp_path / ".summary.json.tmp"]
  assert path.read_text() == "the earlier run's"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_free_space_note_in_mebibytes_or_nothing(tmp_path, monkeypatch):
  real = shutil.disk_usage
  monkeypatch.setattr(_files.shutil, "disk_usage",
                      lambda folder: real(folder)._replace(free=5 * 2**20 + 2**19))
  assert _files.free_space_note(tmp_path) == f"; 5.5 {_files.FREE_SPACE}"
  monkeypatch.undo()
  assert _files.free_space_note(tmp_path / "gone") == ""  # unknown: no note, no error


# ---------------------------------------------------------------- _locks
def test_a_folder_lock_refuses_a_second_holder_naming_the_first(tmp_path):
  lock = _locks.FolderLock(tmp_path, ".x.lock")
  assert (tmp_path / ".x.lock").read_text() == HOLDER
  with pytest.raises(_locks.FolderBusyError, match=f"is in use by {HOLDER}$") as e:
    _locks.FolderLock(tmp_path, ".x.lock")
  assert e.value.holder == HOLDER and e.value.folder == tmp_path
  assert (tmp_path / ".x.lock").read_text() == HOLDER  # the refused one changed nothing
  lock.release()
  lock.release()  # a second release does nothing (its descriptor is not closed twice)
  assert not (tmp_path / ".x.lock").exists()
  _locks.FolderLock(tmp_path, ".x.lock").release()  # free again


def test_a_lock_file_no_process_holds_is_taken_over_and_rewritten(tmp_path):
  (tmp_path / ".x.lock").write_text("a-killed-run-on-a-host-with-a-long-name 4194304")
  lock = _locks.FolderLock(tmp_path, ".x.lock")
  assert (tmp_path / ".x.lock").read_text() == HOLDER
  lock.release()


def test_a_lock_dropped_without_release_is_freed(tmp_path):
  lock = _locks.FolderLock(tmp_path, ".x.lock")
  del lock
  gc.collect()
  assert not (tmp_path / ".x.lock").exists()  # released as release() does: file removed
  _locks.FolderLock(tmp_path, ".x.lock").release()  # (raises FolderBusyError if still held)
  assert not (tmp_path / ".x.lock").exists()


def test_a_refused_lock_leaves_nothing_to_clean_up(tmp_path, monkeypatch):
  unraisable = []
  monkeypatch.setattr("sys.unraisablehook", unraisable.append)
  lock = _locks.FolderLock(tmp_path, ".x.lock")
  with pytest.raises(_locks.FolderBusyError):
    _locks.FolderLock(tmp_path, ".x.lock")
  gc.collect()
  lock.release()
  assert not unraisable, [u.exc_value for u in unraisable]


@pytest.mark.parametrize("after_release", ["nothing", "another process locks a new file"])
def test_a_lock_taken_as_its_holder_removes_the_file_is_on_the_file_at_the_path(
    tmp_path, monkeypatch, after_release):
  # The holder ends between our open() and flock(): its file is unlinked, and our flock
  # succeeds on that unlinked file. Holding it would let a third process create the file
  # anew and lock it too: two writers in one folder.
  path = tmp_path / ".x.lock"
  path.write_text("ending 1")
  real_flock, calls, others = _locks.fcntl.flock, [], []

  def flock(fd, op):
    calls.append(fd)
    if len(calls) == 1:
      path.unlink()  # the holder's release
      if after_release != "nothing":
        others.append(_locks.FolderLock(tmp_path, ".x.lock"))
    return real_flock(fd, op)

  monkeypatch.setattr(_locks.fcntl, "flock", flock)
  if after_release == "nothing":
    lock = _locks.FolderLock(tmp_path, ".x.lock")
    assert os.stat(path).st_ino == os.fstat(lock._fd).st_ino  # pylint: disable=protected-access
    with pytest.raises(_locks.FolderBusyError):
      _locks.FolderLock(tmp_path, ".x.lock")
    lock.release()
  else:
    with pytest.raises(_locks.FolderBusyError):
      _locks.FolderLock(tmp_path, ".x.lock")
    others[0].release()


def test_output_lock_removes_only_the_folders_it_made_and_left_empty(tmp_path):
  out = tmp_path / "a" / "b"
  with _locks.output_lock(out, ".l", "busy {holder}"):
    assert (out / ".l").read_text() == HOLDER
  assert not (tmp_path / "a").exists()  # made for the run, left empty: removed
  (tmp_path / "mine").mkdir()  # the user's empty folder stays
  with _locks.output_lock(tmp_path / "mine" / "new", ".l", "busy {holder}"):
    pass
  assert [p.name for p in tmp_path.iterdir()] == ["mine"] and not any(
      (tmp_path / "mine").iterdir())
  with pytest.raises(ValueError), _locks.output_lock(out, ".l", "busy {holder}"):
    (out / "result.npy").write_bytes(b"x")  # a run that wrote, then failed
    raise ValueError
  assert sorted(p.name for p in out.iterdir()) == ["result.npy"]  # kept; the lock is gone
  _locks.FolderLock(out, ".l").release()


def test_output_lock_refused_names_the_holder_in_a_path_with_braces(tmp_path):
  out = tmp_path / "run{1}"
  out.mkdir()
  held = _locks.FolderLock(out, ".l")
  try:
    with pytest.raises(FileExistsError) as e, _locks.output_lock(
        out, ".l", f"another run ({{holder}}) is writing into {out}"):
      pytest.fail("the block ran")
    assert str(e.value) == f"another run ({HOLDER}) is writing into {out}"
    assert (out / ".l").read_text() == HOLDER  # the holder's lock is untouched
  finally:
    held.release()


# ---------------------------------------------------------------- _signals
@pytest.fixture
def python_ctrl_c():
  """Python's own SIGINT handler (pytest-xdist's workers ignore SIGINT), put back after."""
  before = signal.signal(signal.SIGINT, signal.default_int_handler)
  yield
  signal.signal(signal.SIGINT, before)
  _signals._interrupted.clear()  # pylint: disable=protected-access


def _ctrl_c():
  os.kill(os.getpid(), signal.SIGINT)


def _not_interrupted():
  """`raise_if_interrupted` raises nothing (a failure, not an interrupt of pytest)."""
  try:
    _signals.raise_if_interrupted()
  except KeyboardInterrupt:
    pytest.fail("a Ctrl-C that was dealt with (or forgotten) was raised again")


@pytest.mark.usefixtures("python_ctrl_c")
def test_a_held_ctrl_c_goes_to_the_handler_before_after_the_block(caplog):
  calls = []
  signal.signal(signal.SIGINT, lambda signum, frame: calls.append(signum))  # a run's own
  with caplog.at_level("WARNING", logger="sav_jax._signals"):
    with _signals.interrupt_after("Ctrl-C: finishing the save first"):
      _ctrl_c()
      assert not calls  # held back
  assert calls == [signal.SIGINT]  # once, and no KeyboardInterrupt
  assert "Ctrl-C: finishing the save first" in caplog.text
  signal.signal(signal.SIGINT, signal.SIG_DFL)  # the default action: an interrupt after
  with pytest.raises(KeyboardInterrupt):
    with _signals.interrupt_after():
      _ctrl_c()
  assert signal.getsignal(signal.SIGINT) == signal.SIG_DFL
  signal.signal(signal.SIGINT, signal.SIG_IGN)  # ignored (a background job): nothing to hold
  with _signals.interrupt_after("held"):
    assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    _ctrl_c()


@pytest.mark.usefixtures("python_ctrl_c")
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # (the drops)
def test_remembered_interrupts_raise_at_once_and_keep_only_dropped_ones():
  with _signals.remembered_interrupts():
    with pytest.raises(KeyboardInterrupt):  # the handler before still runs where it lands
      _ctrl_c()
    _signals._interrupted.clear()  # pylint: disable=protected-access
    drop_ctrl_c_in_gc()
    with pytest.raises(KeyboardInterrupt):
      _signals.raise_if_interrupted()
    _not_interrupted()  # raised once
    with _signals.remembered_interrupts():  # nested (a command inside a command)
      drop_ctrl_c_in_gc()
    with pytest.raises(KeyboardInterrupt):  # the inner block did not forget it
      _signals.raise_if_interrupted()
    drop_ctrl_c_in_gc()  # dropped, and never raised again inside the block
  _not_interrupted()  # outside: forgotten (a later call is not interrupted)
  assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
  with pytest.raises(ValueError), _signals.remembered_interrupts():
    drop_ctrl_c_in_gc()
    raise ValueError  # the block fails otherwise: still forgotten after it
  _not_interrupted()
  assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@pytest.mark.usefixtures("python_ctrl_c")
def test_ctrl_c_helpers_outside_the_main_thread_run_the_block_as_it_is():
  ran, errors = [], []

  def work():
    try:
      with _signals.interrupt_after("note"), _signals.remembered_interrupts():
        ran.append(True)
    except Exception as e:  # pylint: disable=broad-except
      errors.append(e)

  thread = threading.Thread(target=work)
  thread.start()
  thread.join()
  assert ran == [True] and not errors, errors


# ---------------------------------------------------------------- _checks
def test_plural_and_integers():
  assert [_checks.plural(n, "sequence") for n in (0, 1, 2)] == [
      "0 sequences", "1 sequence", "2 sequences"]
  assert _checks.plural(3, "process", "processes") == "3 processes"
  assert _checks.is_int(3) and _checks.is_int(np.int64(3)) and _checks.is_int(np.uint8(0))
  assert not any(_checks.is_int(x) for x in (True, np.bool_(True), 3.0, "3", None))
  assert [_checks.scientific_integer(t) for t in ("1e3", "+2E2", " 1.25e2 ", "1.e1")] == [
      1000, 200, 125, 10]
  assert not any(_checks.scientific_integer(t) is not None
                 for t in ("1.25e1", "1e-3", "12", "1e", "e3", "1e1234", "-1e3x", "nan"))


def test_the_suites_longest_files_exist_and_are_collected_first(request):
  from tests import conftest  # pylint: disable=import-outside-toplevel
  longest = [conftest.ROOT / "tests" / name for name in conftest.LONGEST_FILES]
  assert all(path.is_file() for path in longest), longest  # (a renamed file would drop out)
  files = list(dict.fromkeys(item.path for item in request.session.items))  # in run order
  collected = [path for path in longest if path in files]
  assert files[:len(collected)] == collected


def test_widened_keeps_every_value_of_ml_dtypes_arrays():
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  for dtype in (ml_dtypes.bfloat16, ml_dtypes.float8_e4m3fn, ml_dtypes.float8_e5m2):
    a = np.asarray([0.5, -1.75, 3.0], dtype)
    w = _checks.widened(a)
    assert w.dtype == np.float32, dtype
    np.testing.assert_array_equal(w, [0.5, -1.75, 3.0])
  f16 = np.asarray([1.5], np.float16)
  assert _checks.widened(f16) is f16  # NumPy's own types as they are


def test_loads_json_nested_too_deeply_is_a_value_error():
  with pytest.raises(ValueError, match="nested too deeply"):
    _checks.loads_json("[" * 200_000 + "]" * 200_000)
  with pytest.raises(ValueError, match=r"^Expecting property name .*line 1 column 2"):
    _checks.loads_json("{not json")  # json's own error (a ValueError), not another one
  assert _checks.loads_json('{"a": [1]}') == {"a": [1]}


def _in_folder_of(module, source: str, name: str):
  """Function `name` of `source`, compiled as if it were a file of `module`'s package."""
  namespace = {"warnings": __import__("warnings"), "_checks": _checks}
  folder = os.path.dirname(os.path.abspath(module.__file__))
  exec(compile(source, os.path.join(folder, "_a_test_frame.py"), "exec"), namespace)  # pylint: disable=exec-used
  return namespace[name]


def test_warnings_name_the_first_caller_outside_sav_jax_flax_and_jax():
  import flax  # pylint: disable=import-outside-toplevel
  import jax  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  check = _in_folder_of(sav_jax, "def check():\n"
                        "  warnings.warn('odd', stacklevel=_checks.caller_stacklevel())\n", "check")
  apply = _in_folder_of(flax, "def apply(f):\n  return f()\n", "apply")
  traced = _in_folder_of(jax, "def traced(f, g):\n  return f(g)\n", "traced")
  with pytest.warns(UserWarning, match="odd") as record:
    line = __import__("inspect").currentframe().f_lineno + 1
    traced(apply, check)  # this line -> JAX -> Flax -> sav_jax's check
  assert (record[0].filename, record[0].lineno) == (__file__, line)


def test_frame_values_at_the_edges_of_what_passes():
  import warnings  # pylint: disable=import-outside-toplevel
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    _checks.check_video_values(np.zeros((2, 4, 4, 3), np.float32))  # black: no 0..1 warning
    _checks.check_video_values(np.full((1, 2, 2, 3), 255, np.int32))
  for empty in (np.zeros((0, 4, 4, 3), np.float32), np.zeros((2, 0, 4, 3), np.int16)):
    _checks.check_video_values(empty)  # no values to refuse (a numpy error before)
  with pytest.raises(ValueError, match="frames of dtype bool"):
    _checks.check_video_values(np.zeros((0, 4, 4, 3), bool))
  with pytest.raises(ValueError, match=r"int32 values 0\.\.256 are outside 0\.\.255 in frame\(s\) "
                     r"\[1\] \(convert 16-bit frames to 8-bit first"):
    _checks.check_video_values(np.int32([[[[0]]], [[[256]]]]))
  with pytest.raises(ValueError, match=r"non-finite values \(NaN/inf\) in frame\(s\) \[0, 2\]"):
    _checks.check_video_values(np.float32([[[[np.inf]]], [[[9]]], [[[-np.inf]]]]))
  # far below 0 and far above 255 at once: the advice for negative values (no 16-bit frame
  # has any)
  with pytest.warns(UserWarning, match="negative values are no image's"):
    _checks.check_video_values(np.float32([[[[-100.0, 1000.0, 9]]]]))


def test_float_frame_ranges_at_the_warning_bounds():
  """The bounds of the value ranges float frames are warned about or refused for: -64 and
  320 (a resize's overshoot of 0..255 frames) pass, a maximum of 1.5 is 0..1 images, values
  below -1 with none above 3 are normalised frames."""
  def looks(values):
    video = np.float32(values).reshape(1, 1, -1, 1)
    return _checks.float_frames_range(video, float(video.min()), float(video.max()))[0]

  assert [looks(v) for v in ([-64.0, 9], [9, 320.0], [-63.5, 319.5], [0, 1.5], [0, 1.6])] == [
      None, None, None, "0..1", None]
  assert [looks(v) for v in ([-64.5, 9], [9, 320.5])] == ["negative", "16-bit"]
  # 0.5% of the values above 1.5: more than the 0.1% (hot pixels) that 0..1 images may have
  assert looks([200.0] * 5 + [0.5] * 995) is None
  # normalised frames: below -1 with none above 3
  with pytest.raises(ValueError, match="look normalised"):
    _checks.check_video_values(np.float32([[[[-1.5, 3.0]]]]))
  assert not _checks.check_video_values(np.float32([[[[-1.0, 3.0]]]]))  # a resize's overshoot


def test_frame_values_without_warnings_say_whether_they_would_warn():
  import warnings  # pylint: disable=import-outside-toplevel
  unit = np.float32([[[[0.2, 0.9, 0.5]]]])
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert _checks.check_video_values(unit, warn=False)  # 0..1 frames: it would warn
    assert not _checks.check_video_values(unit * 255, warn=False)
    assert not _checks.check_video_values(np.int32([[[[0, 1]]]]), warn=False)  # floats only
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255"):
    assert _checks.check_video_values(unit)


def test_frames_in_minus_one_to_one_are_told_how_to_get_0_255():
  """-1..1 frames (the model's own normalisation) were told to multiply by 255 (-255..255)."""
  frames = np.float32([[[[-1.0, 0.2, 1.0]]]])
  video_check = metrics._check_video_values  # pylint: disable=protected-access
  for check in (lambda: _checks.check_video_values(frames, "left"),
                lambda: video_check(frames, "video"), lambda: viz.as_uint8_image(frames)):
    with pytest.warns(UserWarning, match=r"\(frames \+ 1\) \* 127\.5 for -1\.\.1 frames"):
      check()


def test_a_name_of_other_bytes_than_utf8_is_refused():
  _checks.check_utf8_path("caf\u00e9/video.mp4")  # UTF-8 text: passes
  with pytest.raises(ValueError, match=r"'caf\\udce9': the video's name is not UTF-8 text "
                     r"\(bytes of another encoding at character 3"):
    _checks.check_utf8_path("caf\udce9", "video")  # Latin-1's 0xe9 kept as a surrogate


def test_the_value_sample_of_a_large_video_is_about_its_size():
  video = np.broadcast_to(np.float32(7), (10, 500, 600, 3))  # 9M values (a view: no memory)
  sample = _checks._sample(video)  # pylint: disable=protected-access
  assert 100_000 <= sample.size <= 400_000 and np.all(sample == 7)
