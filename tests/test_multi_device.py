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

import numpy as np
import pytest

from sav_jax import inference

ROOT = pathlib.Path(__file__).resolve().parents[1]
ATOL = 1e-4  # px, the fixture README's criterion for final disparities


@pytest.fixture(scope="module")
def child(module_tmp_path):
  out = module_tmp_path / "result.npz"
  env = dict(os.environ, JAX_PLATFORMS="cpu", TF_CPP_MIN_LOG_LEVEL="1",
             XLA_FLAGS="--xla_force_host_platform_device_count=3",
             PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
  proc = subprocess.run([sys.executable, "-m", "tests.test_multi_device", str(out)], cwd=ROOT,
                        env=env, capture_output=True, text=True, timeout=900, check=False)
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
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


def test_infer_command_runs_on_two_devices(child):
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
  long2 = predict(long_left, long_right, 2)
  inference._window_programs, inference._dispatch_window = real_programs, real_dispatch
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
  # `sav-jax infer --devices 2` on the golden frames as PNG folders (the same executables).
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
          "--format", "npy", "--devices", "2", "--no-compile-cache"]
  assert cli.main(argv) == 0
  cli2 = np.stack([np.load(root / "infer" / "disparity" / f"{i:06d}.npy") for i in range(21)])
  log["infer_devices"] = json.loads((root / "infer" / "summary.json").read_text())["devices"]
  np.savez(out_path, golden2=golden2, long2=long2, long1=long1, cli2=cli2,
           golden_replicated=golden_replicated, window_replicated=window_replicated,
           window_one=window_one, log=json.dumps(log))


if __name__ == "__main__":
  _child(sys.argv[1])


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
