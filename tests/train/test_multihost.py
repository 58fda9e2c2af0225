"""Two processes on localhost with `jax.distributed` (CPU, one device each) train in lock-step.

`launch` (called by conftest.py's `multihost` job) writes official-layout weights (the
parity fixtures' deterministic recipe) as a .safetensors file, then starts two
`python -m tests.train.test_multihost --child` processes that call
`jax.distributed.initialize` and `train.loop.run` on the same workdir with `init_from`
that file (so each process converts the PyTorch layout itself). Each process reads its
own shard of the data, the global batch spans both, validation gathers predictions across
processes, and each process writes a digest of its copy of the final parameters.
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
  """Writes official-layout init weights, runs the two processes, returns their reports."""
  from sav_jax.convert import save_state_dict  # pylint: disable=g-import-not-at-top
  from tests.conftest import FIXTURES, _load_make_weights  # pylint: disable=g-import-not-at-top
  sd = _load_make_weights().make_state_dict(str(FIXTURES / "sav_manifest.json"), 0)
  save_state_dict(sd, workdir / "init.safetensors")
  # The same weights as `sav-jax convert` writes them (with their `torch_unused` tensors),
  # which each process also reads, into its own device.
  from sav_jax import cli  # pylint: disable=g-import-not-at-top
  assert cli.main(["convert", str(workdir / "init.safetensors"), str(workdir / "converted")]) == 0
  port = _free_port()
  env = conftest.child_env(jobs.cache, llvm_o0=True)  # both compile; they run 2 steps
  procs = []
  for pid in range(2):
    cmd = [sys.executable, "-m", "tests.train.test_multihost", "--child",
           f"--coordinator=127.0.0.1:{port}", f"--process_id={pid}",
           f"--workdir={workdir / 'run'}", f"--init_from={workdir / 'init.safetensors'}",
           f"--converted={workdir / 'converted'}",
           f"--out={workdir / f'report_{pid}.json'}"]
    procs.append((conftest.start(cmd, env, workdir / f"log_{pid}.txt"), workdir / f"log_{pid}.txt"))
  for proc, log in procs:
    try:
      rc = proc.wait(timeout=900)
    except Exception:  # pylint: disable=broad-except
      for p, _ in procs:
        p.kill()
      raise
    assert rc == 0, f"process exited with {rc}:\n{conftest.tail(log)}"
  reports = [json.loads((workdir / f"report_{i}.json").read_text()) for i in range(2)]
  return {"reports": reports, "workdir": workdir / "run"}


@pytest.mark.train_job("multihost")
def test_two_processes_train_in_lock_step(jobs):
  out = jobs.get("multihost")
  r0, r1 = out["reports"]
  assert (r0["process_index"], r1["process_index"]) == (0, 1)
  assert r0["process_count"] == r1["process_count"] == 2 and r0["device_count"] == 2
  assert r0["step"] == r1["step"] == STEPS
  assert r0["digest"] == r1["digest"]  # identical parameters everywhere
  # A converted folder as init_from reads on each process, the same params as the file's.
  assert r0["converted_digest"] == r0["init_digest"] == r1["converted_digest"]
  assert r0["converted_leaves"] > 400
  ckpt = out["workdir"] / "checkpoints" / str(STEPS)
  for i in range(2):  # each process saved its own data-iterator state
    assert (ckpt / "data" / f"process_{i}-of-2.json").is_file()
  records = [json.loads(line) for line in (out["workdir"] / "metrics.jsonl").open()]
  train = [r for r in records if r["split"] == "train"]
  assert [r["step"] for r in train] == list(range(1, STEPS + 1))
  assert all(r["finite"] == 1.0 and r["l2_updates"] > 0 for r in train)  # real updates
  val = {r["step"]: r["epe"] for r in records if r["split"] == "val"}  # gathered predictions
  assert sorted(val) == [STEPS] and np.isfinite(val[STEPS])


def _child(argv):
  parser = argparse.ArgumentParser()
  for name in ("coordinator", "workdir", "init_from", "converted", "out"):
    parser.add_argument(f"--{name}")
  parser.add_argument("--process_id", type=int)
  parser.add_argument("--child", action="store_true")
  args = parser.parse_args(argv)
  import jax  # pylint: disable=g-import-not-at-top
  import sav_jax  # pylint: disable=g-import-not-at-top
  jax.distributed.initialize(args.coordinator, 2, args.process_id)
  jax.config.update("jax_transfer_guard", "disallow")
  from train import loop  # pylint: disable=g-import-not-at-top
  config = conftest.tiny_config(
      f"--config.train.num_steps={STEPS}", "--config.train.log_every=1",
      f"--config.eval.every_steps={STEPS}", "--config.eval.at_start=False",
      "--config.eval.num_clips=2",
      "--config.eval.batch_size=2", f"--config.init_from={args.init_from}")
  state = loop.run(config, args.workdir)
  from train import checkpoint as ckpt_lib  # pylint: disable=g-import-not-at-top
  with jax.transfer_guard("allow"):
    cfg = sav_jax.SAVConfig()
    init, converted = (ckpt_lib.load_model_params(p, cfg) for p in (args.init_from, args.converted))
  local = jax.tree.map(lambda x: x.addressable_data(0), state.params)
  report = {"process_index": jax.process_index(), "process_count": jax.process_count(),
            "device_count": jax.device_count(), "step": int(jax.device_get(state.step)),
            "digest": _digest(jax.device_get(local)), "init_digest": _digest(init),
            "converted_digest": _digest(converted),
            "converted_leaves": len(jax.tree.leaves(converted))}
  with open(args.out, "w", encoding="utf-8") as f:
    json.dump(report, f)


if __name__ == "__main__":
  _child(sys.argv[1:])
