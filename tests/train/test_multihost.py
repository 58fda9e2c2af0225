"""Two processes on localhost with `jax.distributed` (CPU, one device each) train in lock-step.

`launch` (called by conftest.py's `multihost` job) exports the learn run's parameters as
an orbax variables directory, then starts two `python -m tests.train.test_multihost
--child` processes that call `jax.distributed.initialize` and `train.loop.run` on the
same workdir with `init_from` that directory. Each process reads its own shard of the
data, the global batch spans both, validation gathers predictions across processes, and
each process writes a digest of its copy of the final parameters.
"""

import argparse
import hashlib
import json
import socket
import sys

import numpy as np
import pytest

from tests.train import conftest

STEPS = 2


def _digest(params) -> str:
  import jax  # pylint: disable=g-import-not-at-top
  h = hashlib.sha256()
  for path, leaf in jax.tree_util.tree_leaves_with_path(params):
    h.update(jax.tree_util.keystr(path).encode())
    h.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
  return h.hexdigest()


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def launch(jobs, workdir):
  """Exports init weights, runs the two processes, returns their reports."""
  import jax  # pylint: disable=g-import-not-at-top
  import orbax.checkpoint as ocp  # pylint: disable=g-import-not-at-top
  from sav_jax.convert import save_variables  # pylint: disable=g-import-not-at-top
  learn = jobs.get("learn")
  with ocp.StandardCheckpointer() as ckptr:
    state = ckptr.restore(learn / "checkpoints" / str(conftest.CHECK_STEP) / "state")
  params = jax.device_get(state["params"])
  save_variables(workdir / "init", {"params": params}, {"source": "learn"})
  port = _free_port()
  procs = []
  for pid in range(2):
    cmd = [sys.executable, "-m", "tests.train.test_multihost", "--child",
           f"--coordinator=127.0.0.1:{port}", f"--process_id={pid}",
           f"--workdir={workdir / 'run'}", f"--init_from={workdir / 'init'}",
           f"--out={workdir / f'report_{pid}.json'}"]
    procs.append((conftest.start(cmd, conftest.child_env(jobs.cache), workdir / f"log_{pid}.txt"),
                  workdir / f"log_{pid}.txt"))
  for proc, log in procs:
    try:
      rc = proc.wait(timeout=900)
    except Exception:  # pylint: disable=broad-except
      for p, _ in procs:
        p.kill()
      raise
    assert rc == 0, f"process exited with {rc}:\n{conftest.tail(log)}"
  reports = [json.loads((workdir / f"report_{i}.json").read_text()) for i in range(2)]
  return {"reports": reports, "init_digest": _digest(params), "workdir": workdir / "run"}


@pytest.mark.train_job("multihost")
def test_two_processes_train_in_lock_step(jobs):
  out = jobs.get("multihost")
  r0, r1 = out["reports"]
  assert (r0["process_index"], r1["process_index"]) == (0, 1)
  assert r0["process_count"] == r1["process_count"] == 2 and r0["device_count"] == 2
  assert r0["step"] == r1["step"] == STEPS
  assert r0["digest"] == r1["digest"]                # identical parameters everywhere
  assert r0["digest"] != out["init_digest"]          # ... and they were trained
  ckpt = out["workdir"] / "checkpoints" / str(STEPS)
  for i in range(2):  # each process saved its own data-iterator state
    assert (ckpt / "data" / f"process_{i}-of-2.json").is_file()
  records = [json.loads(line) for line in (out["workdir"] / "metrics.jsonl").open()]
  assert [r["step"] for r in records if r["split"] == "train"] == list(range(1, STEPS + 1))
  val = [r for r in records if r["split"] == "val"]
  assert len(val) == 1 and np.isfinite(val[0]["epe"])


def _child(argv):
  parser = argparse.ArgumentParser()
  for name in ("coordinator", "workdir", "init_from", "out"):
    parser.add_argument(f"--{name}")
  parser.add_argument("--process_id", type=int)
  parser.add_argument("--child", action="store_true")
  args = parser.parse_args(argv)
  import jax  # pylint: disable=g-import-not-at-top
  jax.distributed.initialize(args.coordinator, 2, args.process_id)
  jax.config.update("jax_transfer_guard", "disallow")
  from absl import flags  # pylint: disable=g-import-not-at-top
  from ml_collections import config_flags  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  config_flags.DEFINE_config_file("config")
  flags.FLAGS([sys.argv[0], f"--config={conftest.ROOT / 'configs' / 'synthetic.py'}",
               *conftest.TINY, f"--config.train.num_steps={STEPS}",
               "--config.train.log_every=1", f"--config.eval.every_steps={STEPS}",
               "--config.eval.num_clips=2", "--config.eval.batch_size=2",
               f"--config.init_from={args.init_from}"])
  state = loop.run(flags.FLAGS.config, args.workdir)
  local = jax.tree.map(lambda x: x.addressable_data(0), state.params)
  report = {"process_index": jax.process_index(), "process_count": jax.process_count(),
            "device_count": jax.device_count(), "step": int(jax.device_get(state.step)),
            "digest": _digest(jax.device_get(local))}
  with open(args.out, "w", encoding="utf-8") as f:
    json.dump(report, f)


if __name__ == "__main__":
  _child(sys.argv[1:])
