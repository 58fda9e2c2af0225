"""Where the forward's time goes, per compiled operation (jax.profiler trace).

    python benchmarks/op_profile.py                       # T=5 128x256 iters=8, float32
    python benchmarks/op_profile.py --top 25 --by module  # the 25 costliest model parts

Compiles the inference forward (random weights, `final_only=True`, the inference compile
options), traces `--repeats` calls with `jax.profiler.trace`, and attributes the time of every
executed XLA operation (thunk) to

- its kind: convolution, matrix product, YNNPACK fusion (a library call that may hold a
  convolution or a product with its elementwise neighbours), XLA loop fusion, copy/transpose,
  reduction, other;
- the model part it came from: the Flax module path in the operation's metadata, cut to
  `--depth` levels (`--by module`).

For every group it prints the time per call, its share, the multiply-adds of the
convolutions and products it ran (from the shapes in the optimized HLO) and the resulting
GFLOP/s, so that parts that run far below the machine's peak stand out (on a GPU the
multiply-adds of the cuDNN convolutions and cuBLAS products XLA calls are counted too, and the
times are those of the device's "XLA Ops" trace lines; written for and run on XLA:CPU, not yet
run on a GPU). Operations inside the
refinement loops are counted once per executed iteration. XLA:CPU runs independent operations
concurrently, so the summed operation time exceeds the wall time and the per-group rates are
lower bounds; the first line gives the rate over the whole call.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import math
import pathlib
import re
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.runtime import inference_compiler_options  # noqa: E402  pylint: disable=wrong-import-position
from timing import (  # noqa: E402  pylint: disable=wrong-import-position
    add_clip_arguments, check_clip_arguments, random_forward)

_COMPUTATION = re.compile(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%?([\w.\-]+) = (.+?) ([\w\-]+)\((.*)$")
_SHAPE = re.compile(r"[a-z]+\d*\[([\d,]*)\]")
_CALLS = re.compile(r"(?:calls|to_apply|body|condition)=%?([\w.\-]+)")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_DIM_LABELS = re.compile(r"dim_labels=(\w+)_(\w+)->(\w+)")
_CONTRACT = re.compile(r"lhs_contracting_dims=\{([\d,]*)\}")
_OPERAND = re.compile(r"%([\w.\-]+)")
_TARGET = re.compile(r'custom_call_target="([^"]*)"')
_GEMM_CONTRACT = re.compile(r'"lhs_contracting_dimensions":\[([^\]]*)\]')
# XLA:GPU's library calls: cuDNN forward convolutions and cuBLAS products.
_CONV_TARGETS = ("__cudnn$convForward", "__cudnn$convBiasActivationForward")
_GEMM_TARGETS = ("__cublas$gemm", "__cublas$lt$matmul")
_LIBRARY_KIND = {"convolution": "cuDNN convolution", "dot": "cuBLAS product"}


def _dims(text: str) -> list[list[int]]:
  return [[int(d) for d in m.group(1).split(",") if d] for m in _SHAPE.finditer(text)]


def _library_call(rest: str) -> str:
  """"convolution" / "dot" for XLA:GPU's cuDNN / cuBLAS custom calls, else ""."""
  target = _TARGET.search(rest)
  if not target:
    return ""
  if target.group(1) in _CONV_TARGETS:
    return "convolution"
  return "dot" if target.group(1) in _GEMM_TARGETS else ""


def _macs(opcode: str, rest: str, out: list[int], shapes: dict[str, list[int]]) -> int:
  """Multiply-adds of a "convolution" or "dot" from its result and operand shapes (XLA's
  own, or the cuDNN/cuBLAS custom call XLA:GPU turns it into: `_library_call`)."""
  names = _OPERAND.findall(rest.split(")")[0])
  if len(names) < 2 or names[1] not in shapes:
    return 0
  n_out = math.prod(out)
  if opcode == "convolution":
    labels = _DIM_LABELS.search(rest)
    if not labels:
      return 0
    # Every output element sums over the kernel's spatial taps and its input features.
    return n_out * math.prod(d for lab, d in zip(labels.group(2), shapes[names[1]]) if lab != "o")
  # XLA's dot: lhs_contracting_dims={1}; cuBLAS's backend config: "lhs_contracting_dimensions":["1"]
  contract = _CONTRACT.search(rest) or _GEMM_CONTRACT.search(rest)
  if not contract or names[0] not in shapes:
    return n_out
  dims = [int(i.strip('" ')) for i in contract.group(1).split(",") if i.strip('" ')]
  return n_out * math.prod(shapes[names[0]][i] for i in dims)


def parse_hlo(text: str) -> dict[str, dict]:
  """Per instruction name: opcode, module path (op_name metadata) and multiply-adds.

  Fusions and calls carry the multiply-adds of the computations they call.
  """
  comps: dict[str, list[tuple[str, str, int, list[str], str]]] = {}
  current, shapes = None, {}
  for line in text.splitlines():
    m = _COMPUTATION.match(line)
    if m and not line[0].isspace():  # a computation's header (instructions are indented)
      current, shapes = comps.setdefault(m.group(1), []), {}
      continue
    m = _INSTRUCTION.match(line)
    if m and current is not None:
      name, result, opcode, rest = m.groups()
      dims = _dims(result)
      shapes[name] = dims[0] if len(dims) == 1 else []
      library = _library_call(rest) if opcode == "custom-call" and dims else ""
      if opcode in ("convolution", "dot"):
        macs = _macs(opcode, rest, shapes[name], shapes)
      elif library:
        macs = _macs(library, rest, dims[0], shapes)  # result: (output, workspace)
        opcode = _LIBRARY_KIND[library]
      else:
        macs = 0
      op_name = _OP_NAME.search(rest)
      current.append((name, opcode, macs, _CALLS.findall(rest),
                      op_name.group(1) if op_name else ""))

  memo: dict[str, int] = {}

  def comp_macs(comp: str) -> int:
    if comp not in memo:
      memo[comp] = 0
      memo[comp] = sum(macs + sum(comp_macs(c) for c in calls if c in comps)
                       for _, opcode, macs, calls, _ in comps.get(comp, [])
                       if opcode not in ("while", "conditional"))
    return memo[comp]

  ops = {}
  for instructions in comps.values():
    for name, opcode, macs, calls, op_name in instructions:
      if opcode in ("while", "conditional"):
        macs_total = 0  # their bodies' operations are traced on their own
      else:
        macs_total = macs + sum(comp_macs(c) for c in calls if c in comps)
      ops[name] = {"opcode": opcode, "macs": macs_total, "op_name": op_name}
  return ops


def kind_of(name: str, op: dict | None) -> str:
  opcode = op["opcode"] if op else ""
  if name.startswith("ynn_fusion") or "ynn" in opcode:
    return "YNNPACK fusion (conv/dot + neighbours)"
  if opcode == "convolution" or opcode in _LIBRARY_KIND.values():
    return opcode
  if opcode == "dot":
    return "matrix product"
  if opcode == "fusion":
    return "XLA loop fusion" if not op["macs"] else "XLA fusion with conv/dot"
  if opcode in ("copy", "transpose"):
    return "copy / transpose"
  if opcode in ("reduce", "reduce-window"):
    return "reduction"
  return f"other ({opcode or name.split('.')[0]})"


_SCAFFOLD = ("while", "body", "cond", "closed_call", "checkpoint", "remat", "rematted_computation")


def module_of(op: dict | None, depth: int) -> str:
  """The Flax module path of an operation (method scopes, jit and loop names dropped)."""
  if not op or not op["op_name"]:
    return "(no metadata)"
  parts = op["op_name"].split("/")[:-1]  # the last part is the primitive
  modules = [p for p in parts if p and "." not in p and "(" not in p and p not in _SCAFFOLD
             and p != "StereoAnyVideo"]
  return "/".join(modules[:depth]) or "(top level)"


def thunk_times(trace_dir: str) -> dict[str, tuple[float, int]]:
  """Per executed HLO operation in the trace under `trace_dir`: (summed us, executions)."""
  files = sorted(pathlib.Path(trace_dir).rglob("*.trace.json.gz"))
  if not files:
    raise FileNotFoundError(f"no perfetto trace written under {trace_dir}")
  with gzip.open(files[-1]) as f:
    data = json.load(f)
  return op_times(data["traceEvents"] if isinstance(data, dict) else data)


def op_times(events: list[dict]) -> dict[str, tuple[float, int]]:
  """Per HLO operation of trace events: (summed us, executions).

  XLA:CPU traces carry one event per executed thunk (`args.hlo_op`) on host threads.
  A GPU trace also has the host's launch events and the streams' kernels; its device
  lines named "XLA Ops" hold one event per executed operation, so where such lines
  exist only they count, else only events of "/device:" processes, else all.
  """
  procs, threads = {}, {}
  for e in events:
    if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name"):
      label = (e.get("args") or {}).get("name", "")
      if e["name"] == "process_name":
        procs[e.get("pid")] = label
      else:
        threads[(e.get("pid"), e.get("tid"))] = label
  op_lines = {k for k, v in threads.items() if v == "XLA Ops"}
  device = {pid for pid, v in procs.items() if v.startswith("/device:")}
  times: dict[str, float] = collections.defaultdict(float)
  counts: dict[str, int] = collections.Counter()
  for e in events:
    if e.get("ph") != "X":
      continue
    args = e.get("args") or {}
    if op_lines:
      if (e.get("pid"), e.get("tid")) not in op_lines:
        continue
      name = args.get("hlo_op") or e.get("name", "")
    elif "hlo_op" in args and (not device or e.get("pid") in device):
      name = args["hlo_op"]
    else:
      continue
    times[name] += float(e.get("dur", 0.0))
    counts[name] += 1
  return {k: (v, counts[k]) for k, v in times.items()}


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p)
  p.add_argument("--dtype", default="float32")
  p.add_argument("--repeats", type=int, default=2, help="traced calls (after one warm-up)")
  p.add_argument("--by", choices=("kind", "module", "op"), default="kind")
  p.add_argument("--depth", type=int, default=3, help="module path levels for --by module")
  p.add_argument("--top", type=int, default=20)
  a = p.parse_args()
  check_clip_arguments(p, a)

  forward, variables, left, right = random_forward(sav_jax.SAVConfig(dtype=a.dtype), a.frames,
                                                   a.height, a.width, a.iters)
  compiled = jax.jit(forward).lower(variables, left, right).compile(
      compiler_options=inference_compiler_options())
  ops = parse_hlo(compiled.as_text())
  compiled(variables, left, right).block_until_ready()  # warm-up
  with tempfile.TemporaryDirectory() as tmp:
    with jax.profiler.trace(tmp, create_perfetto_trace=True):
      t0 = time.perf_counter()
      for _ in range(a.repeats):
        compiled(variables, left, right).block_until_ready()
      wall = (time.perf_counter() - t0) / a.repeats
    times = thunk_times(tmp)

  groups: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0])
  for name, (us, n) in times.items():
    op = ops.get(name)
    if a.by == "kind":
      key = kind_of(name, op)
    elif a.by == "module":
      key = module_of(op, a.depth)
    else:
      key = f"{name} [{module_of(op, 8)}]"
    groups[key][0] += us / a.repeats
    groups[key][1] += (op["macs"] if op else 0) * n / a.repeats
  total = sum(g[0] for g in groups.values())
  macs = sum(g[1] for g in groups.values())
  print(f"T={a.frames} {a.height}x{a.width} iters={a.iters} {a.dtype} "
        f"({jax.devices()[0].device_kind}, jax {jax.__version__}): {wall:.2f} s per call "
        f"(traced), {total / 1e6:.2f} s summed over operations (they overlap); "
        f"{macs / 1e9:.0f} GMAC in convolutions and products = {2 * macs / wall / 1e9:.0f} "
        f"GFLOP/s over the whole call")
  print(f"{'group':64s} {'s/call':>7s} {'share':>6s} {'GMAC':>7s} {'GFLOP/s':>8s}")
  for key, (us, gm) in sorted(groups.items(), key=lambda kv: -kv[1][0])[:a.top]:
    rate = f"{2 * gm / us / 1e3:8.0f}" if gm else f"{'-':>8s}"
    print(f"{key[-64:]:64s} {us / 1e6:7.3f} {100 * us / total:5.1f}% {gm / 1e9:7.2f} {rate}")


if __name__ == "__main__":
  main()
