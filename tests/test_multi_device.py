"""`predict_video(..., devices=n)`: windows run on several devices, same values as on one.

The check runs in a subprocess (`python -m tests.test_multi_device OUT`) with
`XLA_FLAGS=--xla_force_host_platform_device_count=3`, because this process has already
initialised JAX with one CPU device. The child runs the golden_batch_test clip (21 frames
of 28x30, weights seed 0, iters=2) on two devices and compares it with the official
output (its second window, of 11 frames, on the second device), then a 41-frame clip (the
21 frames there and back) on two devices: four windows in two groups, with per-frame
features computed on one device and used on the other, and the 41 frames again on one of
those devices alone, for comparison (with the executables that device already has).
"""

import json
import os
import pathlib
import subprocess
import sys
import types

import numpy as np
import pytest

from sav_jax import inference

ROOT = pathlib.Path(__file__).resolve().parents[1]
ATOL = 1e-4  # px, the fixture README's criterion for final disparities


def _run_child(devices: int, *args, timeout: int) -> None:
  """This file's `__main__` in a process of its own with `devices` fake CPU devices."""
  env = dict(os.environ, JAX_PLATFORMS="cpu", TF_CPP_MIN_LOG_LEVEL="1",
             XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
             PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
  proc = subprocess.run([sys.executable, "-m", "tests.test_multi_device", *map(str, args)],
                        cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout,
                        check=False)
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]


@pytest.fixture(scope="module")
def child(module_tmp_path):
  out = module_tmp_path / "result.npz"
  _run_child(3, out, timeout=900)
  result = dict(np.load(out))
  result["log"] = json.loads(str(result["log"]))
  return result


def test_two_devices_reproduce_the_official_output(child, fixtures_dir):
  ref = np.load(fixtures_dir / "golden_batch_test.npz")["disparity"][:, 0]
  assert child["golden2"].shape == ref.shape == (21, 28, 30)
  err = np.abs(child["golden2"] - ref).max()
  assert err <= ATOL, f"max abs error {err:.2e} px"


def test_windows_run_at_once_on_their_devices(child):
  log = child["log"]
  assert log["devices"] == 3
  # 41 frames: windows [0, 20), [10, 30), [20, 40), [30, 41), two at a time on devices 0, 1.
  assert log["windows"] == [[0, 0], [10, 1], [20, 0], [30, 1]]
  assert log["outputs_on"] == [0, 1, 0, 1]
  # Every frame's features once, in chunks of 10 (the last one frame), each on the device of
  # the first window that needs it ([20, 30) on device 1 in the first group, used on
  # device 0 in the second).
  assert log["chunks"] == [[0, 10, 0], [10, 20, 0], [20, 30, 1], [30, 40, 0], [40, 41, 1]]
  # Per group, every executable is compiled before any work of the group starts.
  assert log["events"] == ["compile"] * 2 + ["run"] * 2 + ["compile"] * 2 + ["run"] * 2
  # Two jitted functions (per-frame features, window) for the six executables of the two
  # devices (features of 10 frames on both, of 1 on one; windows of 20 frames on both, of
  # 11 on one): the second device's reuse the first's traces of a shape. Each compile
  # traced the model anew before (~3-4 s of the 2-core CPU each).
  assert log["model_traces"] == 2


def test_infer_command_runs_on_two_devices(child):
  # --devices all of 3 for 2 windows: summary.json lists the two that ran them (it listed 3)
  assert child["log"]["infer_devices"] == ["cpu:0", "cpu:1"]
  np.testing.assert_array_equal(child["cli2"], child["golden2"])


def test_same_values_as_one_device(child):
  assert child["long2"].shape == child["long1"].shape == (41, 28, 30)
  # Each window runs the same executable on either path, its features computed on its own
  # device or copied from the other: the very same values.
  np.testing.assert_array_equal(child["long2"], child["long1"])


def test_weights_replicated_over_devices_run_on_one(child):
  np.testing.assert_array_equal(child["golden_replicated"], child["golden2"])
  np.testing.assert_array_equal(child["window_replicated"], child["window_one"])


def test_device_choices_are_checked():
  import jax  # pylint: disable=import-outside-toplevel
  n = len(jax.local_devices())
  assert inference.resolve_devices(None) == [jax.devices()[0]]
  assert inference.resolve_devices(1) == jax.local_devices()[:1]
  assert inference.resolve_devices(np.int64(1)) == jax.local_devices()[:1]
  assert inference.resolve_devices("all") == inference.resolve_devices(0) == jax.local_devices()
  assert inference.resolve_devices(jax.local_devices()[-1]) == [jax.local_devices()[-1]]  # one device
  assert inference.resolve_devices(jax.local_devices()) == jax.local_devices()
  with pytest.raises(ValueError, match=f"devices={n + 1}, but {n} local cpu device"):
    inference.resolve_devices(n + 1)
  with pytest.raises(ValueError, match=r"devices must be a number of local devices >= 0 "
                     r"\(0: all\), got -1"):
    inference.resolve_devices(-1)
  for bad in (-1, True, 1.5, "gpu", [], [jax.devices()[0]] * 2, ["cpu:0"], object()):
    with pytest.raises(ValueError, match="devices"):
      inference.resolve_devices(bad)


def test_another_processs_devices_are_refused(monkeypatch):
  import jax  # pylint: disable=import-outside-toplevel
  device = jax.local_devices()[0]
  monkeypatch.setattr(jax, "process_index", lambda: device.process_index + 1)
  with pytest.raises(ValueError, match=r"devices must be this process's own devices "
                     rf"\(jax.local_devices\(\)\), but {device} is process "
                     f"{device.process_index}'s"):
    inference.resolve_devices([device])
  with pytest.raises(ValueError, match="devices must be this process's own devices"):
    inference.resolve_devices(device)  # one device, not in a list: it was taken as it was


def test_windows_at_once_on_cpu_devices_share_the_host_memory(monkeypatch):
  """As many windows at once as there are CPU devices and windows: each takes the estimate
  of one, together at most 1.5x the host's free memory (the margin of one window's check).
  Other devices, and a single CPU device, are left to each device's own check."""
  import sav_jax  # pylint: disable=import-outside-toplevel
  cfg = sav_jax.SAVConfig()
  one = inference.estimate_memory_bytes(20, 32, 32, 2, cfg)
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 2 * one)
  cpu, gpu = types.SimpleNamespace(platform="cpu"), types.SimpleNamespace(platform="gpu")

  def check(devices, frames):
    inference._check_shared_host_memory(  # pylint: disable=protected-access
        devices, inference.window_plan(frames), (32, 32), cfg, 2)

  check([cpu] * 3, 45)  # 3 windows at once: 1.5x the free memory
  check([cpu] * 5, 25)  # 2 windows: 2 devices
  check([cpu, gpu, gpu, gpu], 45)
  with pytest.raises(inference.InsufficientMemoryError,
                     match=r"^4 20-frame windows of 32x32 \(padded\) at once, one per CPU "
                     r"device, need about"):
    check([cpu] * 5, 45)  # 4 windows
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 1)
  check([cpu], 45)


def _golden_clip(fixtures_dir):
  """The golden_batch_test frames, `(left, right)` `[21, 28, 30, 3]`."""
  g = np.load(fixtures_dir / "golden_batch_test.npz")
  video = np.transpose(g["stereo_video"], (0, 1, 3, 4, 2))  # [T, 2, H, W, 3]
  return video[:, 0], video[:, 1]


def _long_clip(fixtures_dir):
  """The 21 golden frames there and back: 41 frames."""
  return tuple(np.concatenate([v, v[::-1][1:]]) for v in _golden_clip(fixtures_dir))


def _child(out_path):
  """Runs in a fresh process with 3 CPU devices."""
  import jax  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  from tests.conftest import FIXTURES, _load_make_weights  # pylint: disable=import-outside-toplevel
  jax.config.update("jax_disable_most_optimizations", True)  # as tests/test_inference.py
  jax.config.update("jax_default_matmul_precision", "highest")
  sd = _load_make_weights().make_state_dict(str(FIXTURES / "sav_manifest.json"), 0)
  variables = sav_jax.convert.params_from_state_dict(sd, sav_jax.SAVConfig())
  left, right = _golden_clip(FIXTURES)
  log = {"devices": jax.device_count(), "windows": [], "outputs_on": [], "chunks": [],
         "events": []}
  real_programs, real_dispatch = inference._window_programs, inference._dispatch_window
  real_model = inference._model
  log["model_traces"] = 0

  def model(cfg):  # built once per jitted function, which keeps its traces
    log["model_traces"] += 1
    return real_model(cfg)

  def programs(*args, **kwargs):
    log["events"].append("compile")
    return real_programs(*args, **kwargs)

  def dispatch(variables, left, right, todo, programs, *, pads, cache, start):
    device = inference._device_of(variables)
    log["events"].append("run")
    log["windows"].append([start, device.id])
    log["chunks"] += [[start + a, start + b, device.id] for a, b in todo]
    raw = real_dispatch(variables, left, right, todo, programs, pads=pads, cache=cache,
                        start=start)
    log["outputs_on"].append(next(iter(raw.devices())).id)
    return raw

  def predict(l, r, devices):
    return inference.predict_video(variables, l, r, iters=2, devices=devices)

  long_left, long_right = _long_clip(FIXTURES)
  inference._window_programs, inference._dispatch_window = programs, dispatch
  inference._model = model
  long2 = predict(long_left, long_right, 2)
  inference._window_programs, inference._dispatch_window = real_programs, real_dispatch
  inference._model = real_model
  golden2 = predict(left, right, 2)
  long1 = predict(long_left, long_right, jax.devices()[1:2])  # one device
  # Weights replicated over a mesh (a training run's) with devices=None: they failed with
  # JAX's sharding mismatch after the per-frame program had run.
  from jax.sharding import Mesh, NamedSharding, PartitionSpec  # pylint: disable=import-outside-toplevel
  replicated = jax.device_put(variables, NamedSharding(Mesh(np.array(jax.devices()), ("x",)),
                                                       PartitionSpec()))
  golden_replicated = inference.predict_video(replicated, left, right, iters=2)
  window_replicated = inference.run_window(replicated, left[:20], right[:20],
                                           cfg=sav_jax.SAVConfig(), iters=2)
  window_one = inference.run_window(variables, left[:20], right[:20], cfg=sav_jax.SAVConfig(),
                                    iters=2)
  # `sav-jax infer --devices all` on the golden frames as PNG folders (the same executables):
  # its two windows on two of the three devices (summary.json listed all three as used).
  import cv2  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  root = pathlib.Path(out_path).parent
  np.savez(root / "weights.npz", **sd)
  for name, frames in (("left", left), ("right", right)):
    (root / name).mkdir()
    for i, frame in enumerate(frames):
      cv2.imwrite(str(root / name / f"{i:06d}.png"), frame[..., ::-1].astype(np.uint8))
  argv = ["infer", "--left", str(root / "left"), "--right", str(root / "right"),
          "--checkpoint", str(root / "weights.npz"), "--out", str(root / "infer"), "--iters", "2",
          "--format", "npy", "--devices", "all", "--no-compile-cache"]
  assert cli.main(argv) == 0
  cli2 = np.stack([np.load(root / "infer" / "disparity" / f"{i:06d}.npy") for i in range(21)])
  log["infer_devices"] = json.loads((root / "infer" / "summary.json").read_text())["devices"]
  np.savez(out_path, golden2=golden2, long2=long2, long1=long1, cli2=cli2,
           golden_replicated=golden_replicated, window_replicated=window_replicated,
           window_one=window_one, log=json.dumps(log))


def _plumbing_child(out_path):
  """Runs in a fresh process with 8 CPU devices: `predict_video`'s placement of windows and
  per-frame features, with stand-ins for the compiled programs (pointwise functions of the
  frames: no model compile), and the training mesh's shardings."""
  import signal  # pylint: disable=import-outside-toplevel
  import jax  # pylint: disable=import-outside-toplevel
  from jax.sharding import Mesh, NamedSharding, PartitionSpec  # pylint: disable=import-outside-toplevel
  from sav_jax import _signals  # pylint: disable=import-outside-toplevel
  from tests.conftest import drop_ctrl_c_in_gc  # pylint: disable=import-outside-toplevel
  from train import state as state_lib  # pylint: disable=import-outside-toplevel
  devs = jax.devices()
  res = {"devices": jax.device_count(),
         "resolved": {str(k): [d.id for d in inference.resolve_devices(k)]
                      for k in (8, 0, "all", 3)}}
  try:
    inference.resolve_devices(9)
  except ValueError as e:
    res["nine"] = str(e)
  # Frame t of the left view holds t + a pattern, the right view 0: the stand-in disparity of
  # frame t is 2 * (t + pattern) - 1, so every frame's value tells where it came from.
  frames, h, w = 75, 6, 10
  pattern = np.arange(h * w, dtype=np.float32).reshape(h, w) % 7
  left = np.repeat((np.arange(frames, dtype=np.float32)[:, None, None] + pattern)[..., None], 3, -1)
  right = np.zeros_like(left)
  want = np.abs(2.0 * (np.arange(frames)[:, None, None] + pattern) - 1.0)  # (abs())
  variables = {"params": {"w": np.float32(2.0), "b": np.float32(-1.0)}}
  feature = jax.jit(lambda v, l, r: {"f": ((l - r).mean(-1) * v["params"]["w"])[None]})
  refine = jax.jit(lambda v, feats: feats["f"][0] + v["params"]["b"])
  log, hooks = [], []

  def programs(variables, shape, pads, todo, *, cfg, iters, check_memory):
    device = inference._device_of(variables).id  # pylint: disable=protected-access

    def features(v, l, r):  # l[:, pads[0], pads[2], 0] holds the frames' indices
      log.append(["features", device, [int(t) for t in l[:, pads[0], pads[2], 0]]])
      for hook in hooks:
        hook()
      return feature(v, l, r)

    def window(v, feats):
      log.append(["window", device, sorted({d.id for x in jax.tree.leaves(feats)
                                            for d in x.devices()})])
      return refine(v, feats)

    return {b - a: features for a, b in todo}, window

  inference._window_programs = programs  # pylint: disable=protected-access
  inference.check_variables = lambda *args, **kwargs: None

  def run(name, variables, devices=None):
    log.clear()
    out = inference.predict_video(variables, left, right, iters=2, devices=devices)
    res[name] = {"log": list(log), "max_err": float(np.abs(out - want).max())}

  run("three", variables, 3)
  # What the feature cache holds while a group's results are taken: the frames the next
  # group needs, not the whole group's.
  caches = []

  class Cache(inference.FrameFeatureCache):
    def __init__(self, *args, **kwargs):
      super().__init__(*args, **kwargs)
      caches.append(self)

  inference.FrameFeatureCache = Cache
  res["held"] = [[t, sorted(caches[0].frames)[:1] + sorted(caches[0].frames)[-1:]]
                 for t, _ in inference.iter_predict_video(variables, left, right, iters=2,
                                                          devices=3)]
  inference.FrameFeatureCache = Cache.__bases__[0]
  run("none", variables)
  run("on_five", jax.device_put(variables, devs[5]))
  run("mesh_2_to_4", jax.device_put(variables, NamedSharding(Mesh(np.array(devs[2:5]), ("x",)),
                                                             PartitionSpec())))
  run("seven_four", variables, [devs[7], devs[4]])
  # A Ctrl-C that Python dropped while the first group ran: no second group.
  hooks.append(lambda: hooks.clear() or drop_ctrl_c_in_gc())
  handler = signal.signal(signal.SIGINT, signal.default_int_handler)
  log.clear()
  try:
    with _signals.remembered_interrupts():
      inference.predict_video(variables, left, right, iters=2, devices=3)
    res["ctrl_c"] = "not raised"
  except KeyboardInterrupt:
    res["ctrl_c"] = [entry[1] for entry in log if entry[0] == "window"]
  finally:
    signal.signal(signal.SIGINT, handler)
  # CPU devices share the host's memory: windows that each fit it, but not 3 at once.
  free = inference.available_memory_bytes
  one = inference.estimate_memory_bytes(20, 32, 32, 2, inference.SAVConfig())  # padded 6x10
  inference.available_memory_bytes = lambda device=None: int(one / 1.2)  # margin 1.5: 1 fits
  try:
    inference.predict_video(variables, left, right, iters=2, devices=3)
    res["shared_memory"] = "not raised"
  except inference.InsufficientMemoryError as e:
    res["shared_memory"] = str(e)
  res["shared_memory_one"] = float(np.abs(inference.predict_video(variables, left, right,
                                                                  iters=2) - want).max())
  inference.available_memory_bytes = free
  # The training mesh: one `data` axis over every device, the batch split on it.
  mesh = state_lib.make_mesh()
  batch = jax.device_put(np.arange(32).reshape(16, 2), state_lib.data_sharding(mesh))
  params = jax.device_put(np.arange(4), state_lib.replicated(mesh))
  res["mesh"] = dict(mesh.shape)
  res["batch_shards"] = sorted([s.device.id, *np.asarray(s.data)[:, 0].tolist()]
                               for s in batch.addressable_shards)
  res["param_shards"] = sorted([s.device.id, len(s.data)] for s in params.addressable_shards)
  res["mesh_of_three"] = [d.id for d in state_lib.make_mesh(devs[5:2:-1]).devices.flat]
  res.update(_mesh_of_yours(devs))
  pathlib.Path(out_path).write_text(json.dumps(res))


def _mesh_of_yours(devs) -> dict:
  """Training's validation on a mesh with a second axis: `data` 4 x `model` 2, batch 4 (the
  batch splits over `data` alone: it was refused as not divisible by 8), a stand-in model
  (the clip's ground truth, in the left image's first channel); and a mesh without `data`."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  from jax.sharding import Mesh  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  from train import evaluation, state as state_lib  # pylint: disable=import-outside-toplevel

  class Model:
    def apply(self, variables, left, right, *, iters, final_only):
      del variables, right, iters, final_only
      return sav_jax.SAVOutput(disparities=left[None, ..., 0])

  rng = np.random.default_rng(0)
  clips = []
  for _ in range(5):
    gt = rng.uniform(1.0, 9.0, (2, 4, 6)).astype(np.float32)
    clips.append({"left": np.repeat(gt[..., None], 3, -1), "right": np.zeros((2, 4, 6, 3),
                                                                          np.float32),
                  "disparity": gt, "valid": np.ones((2, 4, 6), bool)})
  config = ml_collections.ConfigDict({"eval": {"batch_size": 4, "iters": 2,
                                               "dataset": "synthetic"}})
  mesh = Mesh(np.array(devs).reshape(4, 2), ("data", "model"))
  out = {}
  try:
    ev = evaluation.Evaluator(config, Model(), state_lib.replicated(mesh), mesh, clips=clips)
    preds = ev.predictions({})
    out["two_axes"] = float(max(np.abs(p - c["disparity"]).max() for p, c in zip(preds, clips)))
  except ValueError as e:
    out["two_axes"] = str(e)
  try:
    state_lib.data_sharding(Mesh(np.array(devs[:2]), ("batch",)))
  except ValueError as e:
    out["no_data_axis"] = str(e)
  return out


if __name__ == "__main__":
  if sys.argv[1] == "--plumbing":
    _plumbing_child(sys.argv[2])
  else:
    _child(sys.argv[1])


@pytest.fixture(scope="module")
def plumbing(module_tmp_path):
  out = module_tmp_path / "plumbing.json"
  _run_child(8, "--plumbing", out, timeout=300)
  return json.loads(out.read_text())


def test_device_counts_of_eight_devices(plumbing):
  assert plumbing["devices"] == 8
  assert plumbing["resolved"] == {"8": list(range(8)), "0": list(range(8)),
                                  "all": list(range(8)), "3": [0, 1, 2]}
  assert plumbing["nine"] == "devices=9, but 8 local cpu devices are available"


def _windows(run):
  return [entry[1] for entry in run["log"] if entry[0] == "window"]


def test_windows_take_turns_on_the_devices_and_every_frame_is_computed_once(plumbing):
  # 75 frames: 7 windows of 20 (stride 10); on 3 devices, groups of 3 consecutive windows.
  three = plumbing["three"]
  assert three["max_err"] == 0.0  # every frame's own value, in order
  assert _windows(three) == [0, 1, 2, 0, 1, 2, 0]
  assert all(entry[2] == [entry[1]] for entry in three["log"] if entry[0] == "window")
  computed = [t for entry in three["log"] if entry[0] == "features" for t in entry[2]]
  assert sorted(computed) == list(range(75))  # once each, wherever a window needs them
  # the features of a window's frames are computed on the device of the first window that
  # needs them: device 1's window [10, 30) computes 20..29 for device 2's [20, 40)
  assert ["features", 1, list(range(20, 30))] in three["log"]
  # while the first group's results are taken, the cache holds frames 30..39 (the next
  # group's first window starts at 30), no earlier ones; nothing at the end
  assert plumbing["held"] == [[0, [30, 39]], [15, [30, 39]], [25, [30, 39]],
                              [35, [60, 69]], [45, [60, 69]], [55, [60, 69]], [65, []]]
  assert _windows(plumbing["seven_four"]) == [7, 4, 7, 4, 7, 4, 7]
  assert plumbing["seven_four"]["max_err"] == 0.0


def test_without_devices_windows_run_where_the_weights_are(plumbing):
  assert _windows(plumbing["none"]) == [0] * 7 and plumbing["none"]["max_err"] == 0.0
  assert _windows(plumbing["on_five"]) == [5] * 7 and plumbing["on_five"]["max_err"] == 0.0
  # replicated over devices 2..4 (not the default one): the first of them
  assert _windows(plumbing["mesh_2_to_4"]) == [2] * 7
  assert plumbing["mesh_2_to_4"]["max_err"] == 0.0


def test_a_dropped_ctrl_c_stops_the_next_group_of_windows(plumbing):
  assert plumbing["ctrl_c"] == [0, 1, 2]  # the first group finished, no other started


def test_windows_at_once_on_cpu_devices_are_checked_against_the_shared_host_memory(plumbing):
  # Each window fits the host's free memory, so each device's own check passed; 3 at once
  # (one per fake CPU device, all in the host's memory) do not, and are refused before
  # anything runs. One device runs them one at a time.
  assert plumbing["shared_memory"].startswith(
      "3 20-frame windows of 32x32 (padded) at once, one per CPU device, need about ")
  assert "whose memory CPU devices share" in plumbing["shared_memory"]
  assert "use fewer devices (devices)" in plumbing["shared_memory"]
  assert plumbing["shared_memory_one"] == 0.0


def test_the_training_mesh_splits_the_batch_and_replicates_the_state(plumbing):
  assert plumbing["mesh"] == {"data": 8}
  # 16 rows over 8 devices: device i holds rows 2i and 2i + 1 (first column 4i, 4i + 2)
  assert plumbing["batch_shards"] == [[i, 4 * i, 4 * i + 2] for i in range(8)]
  assert plumbing["param_shards"] == [[i, 4] for i in range(8)]
  assert plumbing["mesh_of_three"] == [5, 4, 3]  # the devices given, in their order


def test_validation_on_a_mesh_with_other_axes_splits_the_batch_over_data(plumbing):
  assert plumbing["two_axes"] == 0.0  # every clip's prediction, in order
  assert plumbing["no_data_axis"] == ("the mesh has no 'data' axis (its axes: 'batch'): the batch "
                                      "is split over an axis named 'data'")


def test_each_device_keeps_its_own_executables(monkeypatch):
  """The executable cache holds `_CACHE_SIZE` programs per placement (least recently used
  out first), so n devices running a video do not evict each other's."""
  import collections  # pylint: disable=import-outside-toplevel
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(inference, "_COMPILED", collections.OrderedDict())
  monkeypatch.setattr(inference, "_CACHE_SIZE", 3)
  spec = jax.ShapeDtypeStruct((2,), jnp.float32)

  def compile_one(i, placement):
    key = ("test", sav_jax.SAVConfig(), i, (1, 1, 1), (), placement)
    return inference._compile(key, lambda: (lambda v, x: x + v, (spec, spec)), False)

  for i in range(4):
    compile_one(i, frozenset())
  compile_one(9, frozenset({"other device"}))
  assert [(k[2], k[-1]) for k in inference._COMPILED] == [
      (1, frozenset()), (2, frozenset()), (3, frozenset()), (9, frozenset({"other device"}))]
  compile_one(1, frozenset())  # a hit moves it to the end: 2 is now the oldest
  compile_one(4, frozenset())
  assert [k[2] for k in inference._COMPILED] == [3, 9, 1, 4]
