"""Subprocess jobs that compile the real model, shared by the training tests.

Compiling the full model (frozen VDA included) costs about a minute of one CPU core, and
XLA compiles on one thread, so the expensive runs are subprocesses scheduled two at a
time (`_WORKERS`) with a persistent compilation cache shared by all of them: the
kill/resume runs reuse the executables of the learning run. Jobs start when the first
test that needs one asks for the `jobs` fixture: every job that the selected tests (under
xdist: those of the same file) mark with `@pytest.mark.train_job(name)` is queued then,
so that the two slots stay busy; `jobs.get(name)` waits for one.

  learn        python -m train on a tiny synthetic config; validation EPE before/after
  kill_resume  a copy of `learn` SIGKILLed after step K, resumed to step N (needs learn)
  sharding     one step on 8 fake CPU devices vs 1 device (tests/train/test_sharding.py)
  multihost    two processes with jax.distributed on localhost, from official-layout weights
"""

from __future__ import annotations

import ast
import concurrent.futures
import os
import pathlib
import subprocess
import sys
import threading
import time

import pytest

from tests.conftest import TEST_XLA_FLAGS

ROOT = pathlib.Path(__file__).resolve().parents[2]
_WORKERS = 2
_ORDER = ("learn", "sharding", "kill_resume", "multihost")
_DEPENDS = {"kill_resume": ("learn",)}

# The tiny training setup of the subprocess runs: T=2, 32x32, iters=2, batch 2 (1 for
# the single-process runs), with the schedule length fixed so that every run compiles
# the very same train step.
TINY = [
    "--config.data.frames=2", "--config.data.crop=(32, 32)", "--config.train.iters=2",
    "--config.train.batch_size=2", "--config.optimizer.lr=1e-4",
    "--config.optimizer.schedule_steps=400", "--config.optimizer.pct_start=0.02",
    "--config.data.synthetic.max_disparity=10.0", "--config.data.synthetic.num_objects=2",
    "--config.eval.iters=2", "--config.eval.num_clips=8", "--config.eval.batch_size=8",
    "--config.train.progress_bar=False", "--config.data.num_threads=1",
]
LEARN_STEPS = 20
LEARN_EVAL_EVERY = 5  # learn validates at 0, 5, ..., LEARN_STEPS
CHECK_STEP = 10    # kill_resume compares parameters at this step (a checkpoint of learn)
KILL_AFTER = 2     # ... with those of a run killed after this step's checkpoint


def tiny_config(*overrides):
  """configs/synthetic.py with TINY and `overrides` ("--config.a.b=value") applied."""
  from configs import synthetic  # pylint: disable=g-import-not-at-top
  config = synthetic.get_config()
  for item in (*TINY, *overrides):
    key, value = item[len("--config."):].split("=", 1)
    try:
      value = ast.literal_eval(value)
    except (ValueError, SyntaxError):
      pass  # a plain string
    *parents, leaf = key.split(".")
    node = config
    for name in parents:
      node = node[name]
    setattr(node, leaf, value)
  return config


def _environ_copy() -> dict[str, str]:
  """`dict(os.environ)`, again if a key went away while it was copied: the jobs build their
  environments in worker threads while pytest's main thread sets and removes
  PYTEST_CURRENT_TEST at every test phase (a copy then raised KeyError: a flaky failure of
  the job's tests, 2026-12-05)."""
  for _ in range(99):
    try:
      return dict(os.environ)
    except (KeyError, RuntimeError):  # (RuntimeError: the dict changed size while iterated)
      continue
  return dict(os.environ)


def child_env(cache_dir, device_count: int | None = None, llvm_o0: bool = False,
              fast_compile: bool = False) -> dict:
  """Environment of a subprocess: CPU, shared compilation cache, fast LLVM codegen, the
  suite's `TEST_XLA_FLAGS` (the sharding job: 173 -> 159 CPU-seconds).

  `cache_dir`: JAX_COMPILATION_CACHE_DIR; None for a run given `--config.compile_cache`.

  `fast_compile`: most of XLA's HLO optimisations off (`jax_disable_most_optimizations`,
  as the `fast_compile` fixture): the sharding job's two train steps compile in 46-52 s
  instead of 65 s each, its whole run takes 225 instead of 285 CPU-seconds, and its 8- and
  1-device parameters differ as little as with them on (1.5e-8); the learn and kill/resume
  runs together take ~40 CPU-seconds less (slower steps, faster compiles). Not for the
  multihost job, which gains nothing from it on top of `llvm_o0`.

  `llvm_o0`: LLVM at -O0 as well (XLA's HLO passes still run). The tiny train step then
  compiles in ~32 s instead of ~57 s but runs in 0.9 s instead of 0.4 s: a gain for jobs
  that compile much and run few steps (multihost: 343 -> 235 CPU-seconds), none for the
  learning runs (280 vs 285), and the sharding job's 8- and 1-device parameters then
  differ ~10x more (2.1e-7 against 1.5e-8), too close to its 5e-7 tolerance.
  """
  env = _environ_copy()
  env.pop("JAX_COMPILATION_CACHE_DIR", None)
  flags = ["--xla_llvm_disable_expensive_passes=true", *TEST_XLA_FLAGS.split()]
  if llvm_o0:
    flags.append("--xla_backend_optimization_level=0")
  if device_count:
    flags.append(f"--xla_force_host_platform_device_count={device_count}")
  if fast_compile:
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
  if cache_dir is not None:
    env["JAX_COMPILATION_CACHE_DIR"] = str(cache_dir)
  env.update(JAX_PLATFORMS="cpu", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
             XLA_FLAGS=" ".join(flags),
             PYTHONPATH=os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]),
             TF_CPP_MIN_LOG_LEVEL="1")
  return env


def tail(path, n=4000) -> str:
  text = pathlib.Path(path).read_text(errors="replace") if pathlib.Path(path).exists() else ""
  return text[-n:]


def start(cmd, env, log_path) -> subprocess.Popen:
  log = open(log_path, "w")  # pylint: disable=consider-using-with
  return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)


def run(cmd, env, log_path, timeout=900) -> None:
  """Runs `cmd` to completion; fails with the end of its log."""
  proc = start(cmd, env, log_path)
  try:
    rc = proc.wait(timeout=timeout)
  except subprocess.TimeoutExpired:
    proc.kill()
    proc.wait()
    raise AssertionError(f"{cmd} timed out after {timeout}s:\n{tail(log_path)}")
  if rc != 0:
    raise AssertionError(f"{cmd} exited with {rc}:\n{tail(log_path)}")


def train_cmd(jobs, workdir, *overrides) -> list[str]:
  """python -m train on the TINY config, one clip per step (the cheapest learning run),
  with the jobs' compilation cache as `--config.compile_cache`."""
  return [sys.executable, "-m", "train", "--config", str(ROOT / "configs" / "synthetic.py"),
          "--workdir", str(workdir), *TINY, "--config.train.batch_size=1",
          f"--config.compile_cache={jobs.cache}", *overrides]


class Jobs:
  """Runs named jobs on `_WORKERS` threads; `get` waits for (and if needed starts) one."""

  def __init__(self, root: pathlib.Path):
    self.root = root
    self.cache = root / "jax_cache"
    self.cache.mkdir(parents=True, exist_ok=True)
    self._pool = concurrent.futures.ThreadPoolExecutor(_WORKERS)
    self._futures = {}
    self._lock = threading.Lock()
    self.timings = {}

  def want(self, names) -> None:
    """Queues `names` (in `_ORDER`, so that the two slots stay busy)."""
    for name in _ORDER:
      if name in names:
        self._submit(name)

  def _submit(self, name):
    with self._lock:
      if name not in self._futures:
        for dep in _DEPENDS.get(name, ()):  # dependencies are queued first
          if dep not in self._futures:
            self._futures[dep] = self._pool.submit(self._timed, dep)
        self._futures[name] = self._pool.submit(self._timed, name)
      return self._futures[name]

  def _timed(self, name):
    for dep in _DEPENDS.get(name, ()):
      self.get(dep)
    workdir = self.root / name
    workdir.mkdir(exist_ok=True)
    t0 = time.time()
    try:
      return _JOBS[name](self, workdir)
    finally:
      self.timings[name] = time.time() - t0

  def get(self, name):
    return self._submit(name).result()

  def close(self):
    self._pool.shutdown(wait=True, cancel_futures=True)


def _learn(jobs: Jobs, workdir):
  """python -m train: validation every LEARN_EVAL_EVERY steps, checkpoints at CHECK_STEP."""
  run(train_cmd(jobs, workdir, f"--config.train.num_steps={LEARN_STEPS}",
                f"--config.eval.every_steps={LEARN_EVAL_EVERY}",
                f"--config.checkpoint.every_steps={CHECK_STEP}", "--config.checkpoint.keep=0"),
      child_env(None, fast_compile=True), workdir / "log.txt")
  return workdir


def _kill_resume(jobs: Jobs, workdir):
  """The learn run again, SIGKILLed once its checkpoint KILL_AFTER exists, then resumed."""
  cmd = train_cmd(jobs, workdir, f"--config.train.num_steps={LEARN_STEPS}",
                  "--config.eval.every_steps=0", f"--config.checkpoint.every_steps={KILL_AFTER}",
                  "--config.checkpoint.keep=0")
  proc = start(cmd, child_env(None, fast_compile=True), workdir / "killed_log.txt")
  target = workdir / "checkpoints" / str(KILL_AFTER)
  deadline = time.time() + 900
  while not target.is_dir() and proc.poll() is None and time.time() < deadline:
    time.sleep(0.05)
  proc.kill()  # SIGKILL: no clean-up, no final save
  proc.wait()
  assert target.is_dir(), f"no checkpoint {KILL_AFTER} before the kill:\n" + \
      tail(workdir / "killed_log.txt")
  steps = sorted(int(p.name) for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
  resumed_env = dict(child_env(None, fast_compile=True), JAX_LOG_COMPILES="1")  # cache hits
  run(train_cmd(jobs, workdir, f"--config.train.num_steps={CHECK_STEP}",
                "--config.eval.every_steps=0", f"--config.checkpoint.every_steps={CHECK_STEP}",
                "--config.checkpoint.keep=0"), resumed_env, workdir / "resumed_log.txt")
  return {"workdir": workdir, "steps_at_kill": steps, "rc": proc.returncode,
          "reference": jobs.get("learn")}


def _sharding(jobs: Jobs, workdir):
  out = workdir / "result.json"
  run([sys.executable, "-m", "tests.train.test_sharding", str(out)],
      child_env(jobs.cache, device_count=8, fast_compile=True), workdir / "log.txt")
  return out


def _multihost(jobs: Jobs, workdir):
  from tests.train import test_multihost  # pylint: disable=g-import-not-at-top
  return test_multihost.launch(jobs, workdir)


_JOBS = {"learn": _learn, "kill_resume": _kill_resume, "sharding": _sharding,
         "multihost": _multihost}


def pytest_configure(config):
  config.addinivalue_line("markers", "train_job(name): the test uses a subprocess job")


@pytest.fixture(scope="session")
def _job_runner(tmp_path_factory):
  runner = Jobs(tmp_path_factory.mktemp("train_jobs"))
  yield runner
  runner.close()
  for name, seconds in runner.timings.items():
    sys.stderr.write(f"\n[train job] {name}: {seconds:.0f}s")


@pytest.fixture
def jobs(request, _job_runner):
  """The job runner, with the jobs of the selected tests queued.

  Without xdist every selected test's job is queued at the first request. Under xdist
  each worker collects every test but runs only some files (`--dist loadfile`), so only
  the jobs of the requesting test's file are queued there.
  """
  items = request.session.items
  if os.environ.get("PYTEST_XDIST_WORKER"):
    items = [i for i in items if getattr(i, "module", None) is request.module]
  _job_runner.want({n for i in items for m in i.iter_markers("train_job") for n in m.args})
  return _job_runner
