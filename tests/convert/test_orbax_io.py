"""Tests for sav_jax.convert.orbax_io: orbax save/restore of Flax variables and a config."""

import os
import shutil
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.convert import orbax_io
from sav_jax.convert.torch_io import CheckpointError


def _variables():
  return {
      "params": {
          "fnet": {"conv1": {"kernel": jnp.arange(24.0).reshape(2, 3, 2, 2),
                             "bias": jnp.array([0.5, -1.0])}},
          "corr_mlp": {"fc1": {"kernel": np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)}},
          "half": jnp.ones((3,), jnp.bfloat16) * 1.5,
          "steps": jnp.array(7, jnp.int32),
      },
      "buffers": {"pe": jnp.full((1, 4, 2), 0.25)},
  }


_CONFIG = {"model": {"hidden": 128, "encoder": "vits"}, "iters": 20, "scales": [4, 8, 16],
           "note": None, "flag": True}


def _assert_same(restored, original):
  assert jax.tree.structure(restored) == jax.tree.structure(original)
  for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(restored),
                          jax.tree.leaves(original)):
    assert np.asarray(a).dtype == np.asarray(b).dtype, path
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(path))


def test_round_trip_without_target(tmp_path, monkeypatch):
  variables = _variables()
  out = orbax_io.save_variables(tmp_path / "ckpt", variables, _CONFIG)
  assert out == (tmp_path / "ckpt").absolute()
  assert orbax_io.is_variables_checkpoint(out)
  assert not [p for p in os.listdir(tmp_path) if p != "ckpt"]  # no temporary leftovers
  hook = lambda unraisable: None  # noqa: E731
  monkeypatch.setattr(sys, "unraisablehook", hook)
  restored, config = orbax_io.restore_variables(tmp_path / "ckpt")
  assert sys.unraisablehook is hook  # a good checkpoint changes no global state
  _assert_same(restored, variables)
  assert config == _CONFIG
  assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(restored))


def test_round_trip_with_abstract_target(tmp_path):
  variables = _variables()
  orbax_io.save_variables(tmp_path / "ckpt", variables, _CONFIG)
  target = jax.eval_shape(_variables)
  restored, config = orbax_io.restore_variables(tmp_path / "ckpt", target=target)
  _assert_same(restored, variables)
  assert config["scales"] == [4, 8, 16]


def test_missing_parent_folders_are_created(tmp_path):
  # `sav-jax convert x.pth ckpt/sav` with no ckpt/ yet (the README's first example) failed
  # after converting every weight: the clean-up listed the missing parent.
  out = orbax_io.save_variables(tmp_path / "ckpt" / "runs" / "sav", _variables(), _CONFIG)
  _assert_same(orbax_io.restore_variables(out)[0], _variables())
  assert os.listdir(tmp_path / "ckpt" / "runs") == ["sav"]
  (tmp_path / "file").write_text("x")
  with pytest.raises(CheckpointError, match=r"file/sav: cannot create its folder .*file"):
    orbax_io.save_variables(tmp_path / "file" / "sav", _variables(), _CONFIG)
  assert (tmp_path / "file").read_text() == "x"


def test_tuples_in_config_come_back_as_lists(tmp_path):
  orbax_io.save_variables(tmp_path / "c", {"params": {"w": jnp.ones(2)}}, {"shape": (2, 3)})
  assert orbax_io.restore_variables(tmp_path / "c")[1] == {"shape": [2, 3]}


def test_overwrite(tmp_path):
  path = tmp_path / "ckpt"
  orbax_io.save_variables(path, {"params": {"w": jnp.zeros(2)}}, {"v": 1})
  with pytest.raises(FileExistsError, match="overwrite=True"):
    orbax_io.save_variables(path, {"params": {"w": jnp.ones(2)}}, {"v": 2})
  (path / "NOTES.txt").write_text("my notes")  # a user's file in the folder is kept
  orbax_io.save_variables(path, {"params": {"w": jnp.ones(3)}}, {"v": 2}, overwrite=True)
  restored, config = orbax_io.restore_variables(path)
  np.testing.assert_array_equal(restored["params"]["w"], np.ones(3))
  assert config == {"v": 2} and (path / "NOTES.txt").read_text() == "my notes"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]  # no leftovers of the swap
  # The old checkpoint stays whole until the new one is complete.
  with pytest.raises(CheckpointError, match="zero-size"):
    orbax_io.save_variables(path, {"params": {"w": jnp.ones(0)}}, {"v": 3}, overwrite=True)
  np.testing.assert_array_equal(orbax_io.restore_variables(path)[0]["params"]["w"], np.ones(3))


def test_overwrite_through_a_symlink_keeps_the_link(tmp_path):
  # Overwriting used to rename the link itself, then fail in rmtree on the moved link.
  target, link = tmp_path / "run5", tmp_path / "latest"
  orbax_io.save_variables(target, {"params": {"w": jnp.zeros(2)}}, {"v": 1})
  link.symlink_to(target, target_is_directory=True)
  orbax_io.save_variables(link, {"params": {"w": jnp.ones(2)}}, {"v": 2}, overwrite=True)
  assert link.is_symlink() and link.resolve() == target.resolve()
  np.testing.assert_array_equal(orbax_io.restore_variables(target)[0]["params"]["w"], [1, 1])
  assert sorted(p.name for p in tmp_path.iterdir()) == ["latest", "run5"]
  (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
  with pytest.raises(CheckpointError, match="broken symbolic link"):
    orbax_io.save_variables(tmp_path / "gone", {"params": {"w": jnp.ones(2)}}, {})


def test_an_empty_folder_made_for_it_is_written_into(tmp_path):
  # (`mkdir ckpt` first, with or without overwrite): nothing to replace, nothing refused.
  for overwrite in (False, True):
    path = tmp_path / f"empty_{overwrite}"
    path.mkdir()
    orbax_io.save_variables(path, {"params": {"w": jnp.ones(2)}}, {"v": 1}, overwrite=overwrite)
    restored, config = orbax_io.restore_variables(path)
    np.testing.assert_array_equal(restored["params"]["w"], [1, 1])
    assert config == {"v": 1}
  assert sorted(p.name for p in tmp_path.iterdir()) == ["empty_False", "empty_True"]


def test_refuses_to_overwrite_a_file(tmp_path):
  path = tmp_path / "notes.txt"
  path.write_text("keep me")
  with pytest.raises(FileExistsError, match="overwrite=True"):
    orbax_io.save_variables(path, {"params": {"w": jnp.ones(2)}}, {})
  with pytest.raises(CheckpointError, match="is a file, not a checkpoint folder"):
    orbax_io.save_variables(path, {"params": {"w": jnp.ones(2)}}, {}, overwrite=True)
  assert path.read_text() == "keep me"


def test_refuses_to_overwrite_foreign_directory(tmp_path):
  (tmp_path / "data").mkdir()
  (tmp_path / "data" / "precious.txt").write_text("keep me")
  with pytest.raises(CheckpointError, match="refusing to overwrite"):
    orbax_io.save_variables(tmp_path / "data", {"params": {"w": jnp.ones(2)}}, {},
                            overwrite=True)
  assert (tmp_path / "data" / "precious.txt").read_text() == "keep me"
  # Folders of the items' names without orbax's metadata file are not a checkpoint either
  # (its variables/ and config/ would be replaced).
  for item in ("variables", "config"):
    (tmp_path / "data" / item).mkdir()
    (tmp_path / "data" / item / "mine.txt").write_text("keep me")
  assert not orbax_io.is_variables_checkpoint(tmp_path / "data")
  with pytest.raises(CheckpointError, match="refusing to overwrite"):
    orbax_io.save_variables(tmp_path / "data", {"params": {"w": jnp.ones(2)}}, {},
                            overwrite=True)
  assert (tmp_path / "data" / "config" / "mine.txt").read_text() == "keep me"


def test_a_training_step_is_no_variables_checkpoint_and_is_not_replaced(tmp_path):
  # A step folder of `python -m train` has the metadata file and a `config` item, but
  # `state` for `variables`: overwriting it would delete the run's optimizer state.
  step = tmp_path / "checkpoints" / "5"
  for item in ("state", "config"):
    (step / item).mkdir(parents=True)
    (step / item / "mine.txt").write_text("keep me")
  (step / "_CHECKPOINT_METADATA").write_text("{}")
  assert not orbax_io.is_variables_checkpoint(step)
  assert orbax_io.is_orbax_checkpoint(step) and orbax_io.is_orbax_checkpoint(tmp_path)
  with pytest.raises(CheckpointError, match="refusing to overwrite"):
    orbax_io.save_variables(step, {"params": {"w": jnp.ones(2)}}, {}, overwrite=True)
  assert (step / "state" / "mine.txt").read_text() == "keep me"


def test_not_a_checkpoint(tmp_path):
  with pytest.raises(CheckpointError, match="not found"):
    orbax_io.restore_variables(tmp_path / "missing")
  (tmp_path / "file").write_text("x")
  with pytest.raises(CheckpointError, match="not a directory"):
    orbax_io.restore_variables(tmp_path / "file")
  (tmp_path / "dir").mkdir()
  (tmp_path / "dir" / "other.bin").write_bytes(b"")
  with pytest.raises(CheckpointError, match=r"not a sav-jax checkpoint.*other\.bin"):
    orbax_io.restore_variables(tmp_path / "dir")
  # A training run stopped before its first checkpoint (its workdir or checkpoints/ folder).
  run = tmp_path / "run"
  (run / "checkpoints" / "2.orbax-checkpoint-tmp-1").mkdir(parents=True)  # an unfinished save
  (run / "metrics.jsonl").write_text("")
  for where in (run, run / "checkpoints"):
    with pytest.raises(CheckpointError, match=rf"^{where}: a training run without a finished "
                                              rf"checkpoint yet \({run / 'checkpoints'} holds "
                                              "none"):
      orbax_io.restore_variables(where)


def test_bad_inputs(tmp_path):
  with pytest.raises(CheckpointError, match="JSON"):
    orbax_io.save_variables(tmp_path / "a", {"params": {"w": jnp.ones(2)}}, {"f": object()})
  with pytest.raises(CheckpointError, match="must be a dict"):
    orbax_io.save_variables(tmp_path / "b", {"params": {"w": jnp.ones(2)}}, [1])
  with pytest.raises(CheckpointError, match="zero-size"):
    orbax_io.save_variables(tmp_path / "c", {"params": {"w": jnp.ones((0, 2))}}, {})
  for bad, found in (({"w": jnp.ones(2)}, r"\['w'\]"), ([jnp.ones(2)], "list")):  # params only
    with pytest.raises(CheckpointError, match=rf"expected Flax variables \{{'params': \.\.\.\}}, "
                                              rf"found {found} \(pass the whole variables"):
      orbax_io.save_variables(tmp_path / "d", bad, {})
  assert not os.listdir(tmp_path)


def test_mismatched_target(tmp_path):
  orbax_io.save_variables(tmp_path / "ckpt", {"params": {"w": jnp.ones(2)}}, {})
  target = {"params": {"other": jax.ShapeDtypeStruct((2,), jnp.float32)}}
  with pytest.raises(CheckpointError, match=r"the target does not match the checkpoint: 1 "
                     r"missing from the target, e.g. \['params'\]\['w'\]; 1 not in the "
                     r"checkpoint, e.g. \['params'\]\['other'\]$"):
    orbax_io.restore_variables(tmp_path / "ckpt", target=target)


def test_a_target_of_other_arrays_is_refused_also_without_shardings(tmp_path):
  # Orbax checks shapes only for targets with shardings: a jax.eval_shape target (or NumPy
  # arrays) of another model came back silently at the stored shapes, as NumPy arrays.
  import orbax.checkpoint as ocp  # pylint: disable=import-outside-toplevel
  orbax_io.save_variables(tmp_path / "ckpt", {"params": {"w": jnp.ones(3)}}, {"v": 1})
  step = tmp_path / "run" / "checkpoints" / "5"  # a training run's checkpoint
  with ocp.Checkpointer(ocp.CompositeCheckpointHandler(
      state=ocp.PyTreeCheckpointHandler(), config=ocp.JsonCheckpointHandler())) as c:
    c.save(step, args=ocp.args.Composite(state=ocp.args.PyTreeSave(
        {"params": {"w": np.ones(3, np.float32)}, "step": np.int32(5)}),
        config=ocp.args.JsonSave({"v": 1})))
  for where in (tmp_path / "ckpt", tmp_path / "run"):
    for w in (jax.ShapeDtypeStruct((4,), jnp.float32), np.zeros(2, np.float32),
              jax.ShapeDtypeStruct((3, 1), jnp.float32)):  # (also of another rank)
      with pytest.raises(CheckpointError, match=r"the target does not match the checkpoint: 1 "
                         r"array\(s\) of other shapes, e.g. \['params'\]\['w'\] "
                         r"\((4,|2,|3, 1)\) \(stored \(3,\)\)"):
        orbax_io.restore_variables(where, target={"params": {"w": w}})
    restored, config = orbax_io.restore_variables(  # in the target's dtype, with the config
        where, target={"params": {"w": jax.ShapeDtypeStruct((3,), jnp.bfloat16)}})
    assert restored["params"]["w"].dtype == jnp.bfloat16 and config == {"v": 1}
    np.testing.assert_array_equal(restored["params"]["w"], np.ones(3))
  with pytest.raises(CheckpointError, match=r"5: the target must be Flax variables "
                                            r"\{'params': \.\.\.\}, found \['w'\]"):
    orbax_io.restore_variables(step, target={"w": jax.ShapeDtypeStruct((3,), jnp.float32)})
  # A training checkpoint's partial restore (it skips the optimizer state) returned a subset
  # of the parameters, or a target's leaf the checkpoint does not hold, as they were.
  w, v = jax.ShapeDtypeStruct((3,), jnp.float32), jax.ShapeDtypeStruct((1,), jnp.float32)
  for target, problem in (
      ({}, r"1 missing from the target, e.g. \['params'\]\['w'\]$"),
      ({"w": w, "v": v}, r"1 not in the checkpoint, e.g. \['params'\]\['v'\]$")):
    with pytest.raises(CheckpointError, match=problem):
      orbax_io.restore_variables(step, target={"params": target})


@pytest.mark.parametrize("damage", ["truncated", "deleted", "manifest", "config", "listing",
                                    "root"])
def test_corrupt_checkpoint_is_named_as_such(tmp_path, damage, monkeypatch):
  """Damaged files (a copy cut short, a sync that lost files) give one CheckpointError naming
  the folder, not orbax's bare Exception with a TensorStore spec."""
  import gc  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(0)  # random values: too large to be stored inline
  path = orbax_io.save_variables(tmp_path / "ckpt", {"params": {
      "w": rng.normal(size=3000).astype(np.float32),
      "b": rng.normal(size=(50, 50)).astype(np.float32)}}, _CONFIG)
  chunks = list(path.glob("variables/ocdbt.process_*/d/*"))
  assert chunks
  if damage == "manifest":
    (path / "variables" / "manifest.ocdbt").write_bytes(b"xx")
  elif damage == "config":
    (path / "config" / "metadata").write_text("{")
  elif damage == "listing":  # (was "unreadable checkpoint metadata ('NoneType' object ...)")
    (path / "variables" / "_METADATA").unlink()
  elif damage == "root":  # the arrays' metadata: its reads printed hundreds of tracebacks
    shutil.rmtree(path / "variables" / "d")
  for chunk in chunks if damage in ("truncated", "deleted") else ():
    if damage == "truncated":
      chunk.write_bytes(chunk.read_bytes()[:10])
    else:
      chunk.unlink()
  orbax_io.quiet_failed_reads()  # for late reports too, once the test has put its hook back
  unraisable = []
  monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
  with pytest.raises(CheckpointError, match=f"{path}: the checkpoint is corrupt or incomplete"
                     ) as e:
    orbax_io.restore_variables(path)
  assert "TensorStore" not in str(e.value) and len(str(e.value)) < 600
  # the failed restore put its filter in (`!=`: each `.append` is a new bound method); a
  # missing listing is refused before any read
  assert damage == "listing" or sys.unraisablehook != unraisable.append
  gc.collect()  # orbax's other pending reads: no "Exception ignored in <coroutine ...>"
  # (an earlier case's late reports may have reached the list before the filter was in)
  assert not [u for u in unraisable if not orbax_io._is_failed_read_noise(u)], unraisable  # pylint: disable=protected-access


def test_only_the_reports_of_failed_reads_are_dropped(monkeypatch):
  import asyncio  # pylint: disable=import-outside-toplevel
  import types  # pylint: disable=import-outside-toplevel
  seen = []
  monkeypatch.setattr(sys, "unraisablehook", seen.append)
  orbax_io.quiet_failed_reads()
  loop = asyncio.new_event_loop()
  loop.close()
  try:  # what tensorstore's threads hit when a read completes after orbax closed its loop
    loop.call_soon_threadsafe(lambda: None)
  except RuntimeError as e:
    closed = e
  report = lambda e: types.SimpleNamespace(exc_value=e, exc_traceback=e.__traceback__,
                                           object=None)
  mine = [report(RuntimeError("mine")), report(RuntimeError("Event loop is closed here")),
          report(ValueError("Encountered error while reading array index"))]
  for r in [report(Exception("Encountered error while reading array index: (slice(0, 3, 1),).")),
            report(closed), *mine]:
    sys.unraisablehook(r)
  assert seen == mine


@pytest.mark.parametrize("error", [KeyboardInterrupt, OSError])
def test_a_failed_save_leaves_no_temporary_folder(tmp_path, monkeypatch, error):
  # Ctrl-C during orbax's write left `ckpt.orbax-checkpoint-tmp-...` beside the destination
  # (and an OSError named that temporary path).
  import orbax.checkpoint as ocp  # pylint: disable=import-outside-toplevel
  path = tmp_path / "ckpt"
  orbax_io.save_variables(path, {"params": {"w": jnp.zeros(2)}}, {"v": 1})
  other = tmp_path / "fresh.orbax-checkpoint-tmp-1"  # another process's save under way: kept
  other.mkdir()

  def fail(self, directory, *args, **kwargs):
    assert ".orbax-checkpoint-tmp" in str(directory)  # the write has begun
    raise error(28, "No space left on device")

  for name in ("save", "async_save"):
    monkeypatch.setattr(ocp.JsonCheckpointHandler, name, fail)
  for target, overwrite in ((tmp_path / "fresh", False), (path, True)):
    with (pytest.raises(KeyboardInterrupt) if error is KeyboardInterrupt
          else pytest.raises(CheckpointError, match=f"{target}: could not write the "
                             r"checkpoint \(No space left on device\)")):
      orbax_io.save_variables(target, {"params": {"w": jnp.ones(2)}}, {"v": 2},
                              overwrite=overwrite)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt", other.name]
  monkeypatch.undo()
  restored, config = orbax_io.restore_variables(path)  # the old checkpoint is whole
  np.testing.assert_array_equal(restored["params"]["w"], np.zeros(2))
  assert config == {"v": 1}


def test_a_ctrl_c_during_a_restore_is_an_interrupt_after_it_not_a_corrupt_checkpoint():
  """Ctrl-C while orbax reads a good checkpoint was reported as a corrupt one (its cancelled
  reads), or lost in its reader threads; it is held until the restore is done, then raised."""
  import os  # pylint: disable=import-outside-toplevel
  import signal  # pylint: disable=import-outside-toplevel
  done = []

  def restore():
    os.kill(os.getpid(), signal.SIGINT)  # lands while the checkpoint is read
    done.append(True)
    return {"params": {}}

  handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own
  try:
    with pytest.raises(KeyboardInterrupt):
      orbax_io.checked_restore(restore, "ckpt", mismatch=ValueError)
    assert done == [True] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
  finally:
    signal.signal(signal.SIGINT, handler)


def test_the_command_line_exit_after_ctrl_c_skips_pythons_shutdown(tmp_path):
  """After a Ctrl-C during a compilation, Python's shutdown met XLA's threads mid-work and
  `sav-jax infer` died of a segmentation fault after its message: the exit is immediate."""
  import subprocess  # pylint: disable=import-outside-toplevel
  code = ("import atexit, sys\n"
          "atexit.register(lambda: print('python shutdown ran', file=sys.stderr))\n"
          "print('buffered', end='')\n"
          "from sav_jax._signals import exit_interrupted\n"
          "exit_interrupted('tool: interrupted')\n")
  # (stdout block-buffered, as in a pipe: PYTHONUNBUFFERED would hide a missing flush)
  env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
  proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                        timeout=120, check=False, env=env)
  assert proc.returncode == 130 and proc.stdout == "buffered", proc
  assert proc.stderr == "tool: interrupted\n", proc.stderr


def test_declared_sizes_beyond_any_model_are_refused_before_reading(tmp_path, monkeypatch):
  """A checkpoint of a few hundred kB declaring a 24000 x 24000 array used 4.7 GB of host
  memory before the shape check against the model refused it (orbax reads what the metadata
  declares): the metadata's sizes are bounded first."""
  from sav_jax import SAVConfig  # pylint: disable=import-outside-toplevel
  from sav_jax.model import init  # pylint: disable=import-outside-toplevel
  largest = jax.tree.leaves(init.abstract_variables(SAVConfig(vda_encoder="vitl")))
  sizes = [int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in largest]
  assert max(sizes) < orbax_io.MAX_LEAF_BYTES / 4 and sum(sizes) < orbax_io.MAX_TOTAL_BYTES / 2
  assert 24000 * 24000 * 4 > orbax_io.MAX_LEAF_BYTES  # the case above is refused
  path = orbax_io.save_variables(tmp_path / "ckpt", {"params": {
      "w": np.zeros((40, 40), np.float32), "b": np.zeros((30,), np.float32)}}, _CONFIG)
  reads = []
  monkeypatch.setattr(orbax_io, "checked_restore",
                      lambda *a, **k: reads.append(a) or {"variables": {}, "config": {}})
  monkeypatch.setattr(orbax_io, "MAX_LEAF_BYTES", 40 * 40 * 4 - 1)  # the model's bound, scaled
  with pytest.raises(CheckpointError, match=r"ckpt: the checkpoint declares \['params'\]\['w'\] "
                     r"of shape \(40, 40\) \(5\.96e-06 GiB\), larger than any array of the "
                     r"model .*\(nothing was read\)"):
    orbax_io.restore_variables(path)
  monkeypatch.setattr(orbax_io, "MAX_LEAF_BYTES", 2**20)
  monkeypatch.setattr(orbax_io, "MAX_TOTAL_BYTES", 40 * 40 * 4 + 30 * 4 - 1)
  with pytest.raises(CheckpointError, match=r"declares 6.*e-06 GiB of arrays, more than any "
                                            r"model's weights"):
    orbax_io.restore_variables(path)
  assert not reads
  monkeypatch.setattr(orbax_io, "MAX_LEAF_BYTES", 40 * 40 * 4)  # bounds reached, not passed
  monkeypatch.setattr(orbax_io, "MAX_TOTAL_BYTES", 40 * 40 * 4 + 30 * 4)
  orbax_io.restore_variables(path)
  assert len(reads) == 1


@pytest.mark.parametrize("item", ["variables", "state"])
def test_a_pipe_in_a_checkpoint_is_refused_not_waited_on(tmp_path, item):
  """A named pipe in place of a data file made `sav-jax infer` wait forever, Ctrl-C held (in
  a training checkpoint's `state` item: a link to a device)."""
  import orbax.checkpoint as ocp  # pylint: disable=import-outside-toplevel
  w = np.random.default_rng(0).normal(size=3000).astype(np.float32)
  path = tmp_path / "checkpoints" / "5"
  if item == "variables":
    orbax_io.save_variables(path, {"params": {"w": w}}, _CONFIG)
  else:
    with ocp.Checkpointer(ocp.CompositeCheckpointHandler(state=ocp.PyTreeCheckpointHandler())
                          ) as c:
      c.save(path, args=ocp.args.Composite(state=ocp.args.PyTreeSave({"params": {"w": w}})))
  [chunk, *_] = sorted(path.glob(f"{item}/ocdbt.process_*/d/*"))
  chunk.unlink()
  if item == "variables":
    os.mkfifo(chunk)
  else:
    chunk.symlink_to(os.devnull)
  with pytest.raises(CheckpointError, match=rf"{chunk} is not a regular file \(a pipe, socket "
                                            r"or device\)"):
    orbax_io.restore_variables(path)


def test_deeply_nested_config_json_is_named_not_a_recursion_traceback(tmp_path):
  path = orbax_io.save_variables(tmp_path / "ckpt", {"params": {"w": np.ones(3, np.float32)}},
                                 _CONFIG)
  (path / "config" / "metadata").write_text("[" * 100_000 + "]" * 100_000)
  with pytest.raises(CheckpointError, match=r"ckpt: the checkpoint is corrupt or incomplete .*"
                                            r"a JSON file nested too deeply"):
    orbax_io.restore_variables(path)


def test_the_latest_training_step_is_found_by_number(tmp_path):
  # `sav-jax convert WORKDIR out.npz` exports the latest finished step: 10 after 9 (not by
  # name), and not an unfinished save (no metadata) nor a temporary folder.
  for step in ("2", "9", "10", "11.orbax-checkpoint-tmp-1", "12"):
    (tmp_path / "checkpoints" / step / "state").mkdir(parents=True)
    if step != "12":
      (tmp_path / "checkpoints" / step / "_CHECKPOINT_METADATA").write_text("{}")
  want = tmp_path / "checkpoints" / "10"
  for path in (tmp_path, tmp_path / "checkpoints", want):
    assert orbax_io.find_training_checkpoint(path) == want
  assert orbax_io.find_training_checkpoint(tmp_path / "checkpoints" / "12") is None


def test_reading_a_run_names_later_step_folders_that_are_no_checkpoints(tmp_path, caplog):
  # A copy of a run cut short (12 without its metadata): infer, eval, convert and init_from
  # read step 10 without a word, where the run itself refuses the folder.
  import logging  # pylint: disable=import-outside-toplevel
  for step in ("10", "12", "13"):
    (tmp_path / "checkpoints" / step / "state").mkdir(parents=True)
  (tmp_path / "checkpoints" / "10" / "_CHECKPOINT_METADATA").write_text("{}")
  with caplog.at_level(logging.WARNING), pytest.raises(CheckpointError, match="no state/_METADATA|"
                                                       "has no _METADATA"):
    orbax_io.restore_variables(tmp_path)  # (these hand-made folders hold no arrays)
  assert (f"{tmp_path / 'checkpoints'}: [12, 13] named like later checkpoints but have no "
          "_CHECKPOINT_METADATA and state/ (unfinished, or a copy cut short): reading the "
          "latest finished one, step 10") in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING), pytest.raises(CheckpointError):
    orbax_io.restore_variables(tmp_path / "checkpoints" / "10")  # asked for by name: no news
  assert "named like later checkpoints" not in caplog.text


def test_out_of_memory_is_not_reported_as_a_corrupt_checkpoint(tmp_path):
  # Orbax wraps a read that ran out of host memory as it wraps a failed read: a good
  # checkpoint called corrupt may be deleted.
  error = Exception("Encountered error while reading array index: (slice(0, 4, 1),).")
  error.__cause__ = MemoryError("out of memory")
  assert orbax_io.corrupt_checkpoint_error(tmp_path, error) is None
  error.__cause__ = None
  assert "corrupt or incomplete" in str(orbax_io.corrupt_checkpoint_error(tmp_path, error))


def test_a_failed_read_is_found_among_the_causes_of_an_error(tmp_path):
  # Tensorstore's own line (without its spec) names the damaged file, also as the context of
  # the error orbax raised while handling it.
  read = ValueError('OUT_OF_RANGE: Error reading "params.w/0" in OCDBT database at local file '
                    '"d/1" [tensorstore_spec={"driver": "zarr"}]')
  error = RuntimeError("restore failed")
  error.__context__ = read
  assert str(orbax_io.corrupt_checkpoint_error(tmp_path, error)) == (
      f"{tmp_path}: the checkpoint is corrupt or incomplete (a file of it is truncated or "
      'missing): OUT_OF_RANGE: Error reading "params.w/0" in OCDBT database at local file "d/1"')
  assert orbax_io.corrupt_checkpoint_error(tmp_path, RuntimeError("other")) is None


def test_only_errors_of_a_mismatch_are_reported_as_one(tmp_path, monkeypatch):
  """A target that does not fit orbax's read (a ValueError, KeyError, TypeError or IndexError)
  is `mismatch`'s error; any other error propagates as it is."""
  monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # (a failure keeps its filter)

  def restore(error):
    def fail():
      raise error
    return fail

  mismatch = lambda e: CheckpointError(f"mismatch: {e!r}")  # noqa: E731
  with pytest.raises(CheckpointError, match=r"^mismatch: IndexError\('index 3'\)$"):
    orbax_io.checked_restore(restore(IndexError("index 3")), tmp_path, mismatch)
  for error in (RuntimeError, MemoryError):
    with pytest.raises(error, match="^other$"):
      orbax_io.checked_restore(restore(error("other")), tmp_path, mismatch)


def test_a_folder_whose_name_is_not_utf8_is_named_not_a_tensorstore_traceback(tmp_path):
  """Latin-1 bytes (a zip made on Windows): orbax's TensorStore failed deep inside with
  "Unable to cast Python instance of type <class 'str'>" (a RuntimeError, a traceback at the
  command line), after the checkpoint's other files were checked."""
  odd = tmp_path / os.fsdecode(b"caf\xe9")
  ok = tmp_path / "ok"
  orbax_io.save_variables(ok, {"params": {"w": jnp.ones(2)}}, {"v": 1})
  files = sorted(p.name for p in ok.iterdir())
  os.rename(ok, odd)
  message = "': the orbax checkpoint folder's name is not UTF-8 text"
  with pytest.raises(ValueError, match=r"caf\\udce9" + message):
    orbax_io.restore_variables(odd)
  with pytest.raises(ValueError, match=r"caf\\udce9/ckpt" + message):
    orbax_io.save_variables(odd / "ckpt", {"params": {"w": jnp.ones(2)}}, {})
  assert sorted(p.name for p in odd.iterdir()) == files  # (no ckpt folder begun)
