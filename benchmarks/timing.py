"""Shared by the benchmark scripts: the median wall time of a compiled call."""

import importlib.util
import os
import pathlib
import statistics
import time

import jax


def timed(fn, *args, repeats=3):
  """Median seconds of `fn(*args)` over `repeats` calls, after one warm-up call."""
  jax.block_until_ready(fn(*args))
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t0)
  return statistics.median(times)


def add_clip_arguments(parser, frames=5, height=128, width=256, iters=8):
  """The clip shape options shared by the scripts: --frames --height --width --iters (an
  option whose default is None is left out: a script that has no use for it)."""
  for name, default in (("frames", frames), ("height", height), ("width", width),
                        ("iters", iters)):
    if default is not None:
      parser.add_argument(f"--{name}", type=int, default=default)


def check_clip_arguments(parser, args) -> None:
  """`parser.error` naming a clip option the model refuses (`sav-jax bench`'s checks): the
  model's trace failed on it with a traceback naming no flag."""
  from sav_jax.tools.bench import clip_problem  # pylint: disable=import-outside-toplevel
  problem = clip_problem(args)
  if problem:
    parser.error(problem)


def random_forward(cfg, frames, height, width, iters):
  """`(forward, variables, left, right)`: the inference forward (`final_only`, not yet
  jitted) of a model with random weights, and a random stereo clip (right = left shifted)."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel

  model = sav_jax.StereoAnyVideo(cfg)
  variables = jax.device_put(init_variables(cfg, seed=0))
  rng = np.random.default_rng(0)
  left = jnp.asarray(rng.uniform(0, 255, (1, frames, height, width, 3)), jnp.float32)
  right = jnp.roll(left, -4, axis=3)

  def forward(v, l, r):
    return model.apply(v, l, r, iters=iters, final_only=True).disparities

  return forward, variables, left, right


def compile_for_shape(cfg, frames, height, width, iters):
  """`(compiled, seconds)`: the inference forward (`final_only`) compiled with the inference
  compile options for abstract weights and clips `[1, T, H, W, 3]`; nothing is allocated, so
  any shape compiles and `compiled.memory_analysis()` tells what it would need."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel
  from sav_jax.runtime import inference_compiler_options  # pylint: disable=import-outside-toplevel

  model = sav_jax.StereoAnyVideo(cfg)
  variables = jax.eval_shape(lambda: init_variables(cfg, seed=0))
  video = jax.ShapeDtypeStruct((1, frames, height, width, 3), jnp.float32)

  def forward(v, l, r):
    return model.apply(v, l, r, iters=iters, final_only=True).disparities

  t0 = time.perf_counter()
  compiled = jax.jit(forward).lower(variables, video, video).compile(
      compiler_options=inference_compiler_options())
  return compiled, time.perf_counter() - t0


def fixtures_folder(arg=None):
  """The oracle fixtures folder: `arg`, else `SAV_FIXTURES`, else `../shared/fixtures`."""
  root = pathlib.Path(__file__).resolve().parents[1]
  return pathlib.Path(arg or os.environ.get("SAV_FIXTURES", root.parent / "shared" / "fixtures"))


def make_weights_module(fixtures, script: str):
  """The fixtures' `make_weights.py` (the deterministic weights of the parity tests), loaded
  as a module; a missing file ends `script` with a message naming it."""
  path = fixtures / "make_weights.py"
  if not path.is_file():
    raise SystemExit(f"{script}: {path} not found (set SAV_FIXTURES or --fixtures to the "
                     "oracle fixtures folder)")
  spec = importlib.util.spec_from_file_location("make_weights", path)
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod
