"""End-to-end runs of `python -m train` (subprocess jobs of conftest.py).

* learn: a short CPU run on the synthetic config lowers the validation EPE (official
  metric, fixed held-out clips) by a clear margin, and writes JSONL + TensorBoard logs.
* kill_resume: the same run SIGKILLed after its step-KILL_AFTER checkpoint and resumed
  reaches step CHECK_STEP with exactly the parameters, optimizer state, RNG and data
  position of the uninterrupted run.
"""

import json

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from tests.train.conftest import CHECK_STEP, KILL_AFTER, LEARN_STEPS


def _records(workdir):
  with open(workdir / "metrics.jsonl", encoding="utf-8") as f:
    return [json.loads(line) for line in f]


def _state(workdir, step):
  with ocp.StandardCheckpointer() as ckptr:
    return jax.device_get(ckptr.restore(workdir / "checkpoints" / str(step) / "state"))


@pytest.mark.train_job("learn")
def test_synthetic_training_lowers_validation_epe(jobs):
  workdir = jobs.get("learn")
  records = _records(workdir)
  val = {r["step"]: r for r in records if r["split"] == "val"}
  assert sorted(val) == [0, LEARN_STEPS]
  before, after = val[0]["epe"], val[LEARN_STEPS]["epe"]
  assert after < 0.6 * before, (before, after)
  assert np.isfinite(val[LEARN_STEPS]["tepe"])
  train = [r for r in records if r["split"] == "train"]
  assert [r["step"] for r in train] == list(range(10, LEARN_STEPS + 1, 10))
  for key in ("loss", "epe", "1px", "3px", "l2_grads", "l2_params", "l2_updates", "lr"):
    assert all(np.isfinite(r[key]) for r in train), key
  assert train[-1]["num_skipped"] == 0
  assert list((workdir / "tb").glob("events.out.tfevents.*"))


@pytest.mark.train_job("kill_resume")
def test_killed_run_resumes_exactly(jobs):
  result = jobs.get("kill_resume")
  workdir, reference = result["workdir"], result["reference"]
  assert result["rc"] == -9  # SIGKILL
  assert KILL_AFTER in result["steps_at_kill"] and max(result["steps_at_kill"]) < CHECK_STEP
  resumed_train = [r["step"] for r in _records(workdir) if r["split"] == "train"]
  assert resumed_train[-1] == CHECK_STEP
  got, want = _state(workdir, CHECK_STEP), _state(reference, CHECK_STEP)
  assert int(got["step"]) == CHECK_STEP and int(got["num_skipped"]) == 0
  leaves_got, leaves_want = jax.tree.leaves(got), jax.tree.leaves(want)
  assert len(leaves_got) == len(leaves_want) > 400
  for a, b in zip(leaves_got, leaves_want):  # bit-identical: same executable, same data
    np.testing.assert_array_equal(a, b)
  data = lambda w: (w / "checkpoints" / str(CHECK_STEP) / "data" / "process_0-of-1.json"
                    ).read_text()
  assert json.loads(data(workdir)) == json.loads(data(reference))
