"""The profiling helpers behind the figures in benchmarks/README.md."""

import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import op_profile  # noqa: E402  pylint: disable=wrong-import-position,import-error

pytestmark = pytest.mark.usefixtures("fast_compile")  # values and HLO shapes, not speed


def test_multiply_adds_of_a_convolution_and_a_product_from_the_optimized_hlo():
  def fn(x, k, w):
    y = jax.lax.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)),
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return jnp.tanh(y).reshape(-1, 8) @ w

  x, k, w = jnp.ones((2, 6, 10, 4)), jnp.ones((3, 3, 4, 8)), jnp.ones((8, 5))
  ops = op_profile.parse_hlo(jax.jit(fn).lower(x, k, w).compile().as_text())
  conv_macs = 2 * 6 * 10 * 8 * (3 * 3 * 4)  # every output element: 3x3 taps x 4 channels
  dot_macs = (2 * 6 * 10) * 5 * 8
  # Whatever XLA fuses, the products it runs carry these multiply-adds, and no operation
  # is charged more than both together.
  macs = {op["macs"] for op in ops.values() if op["macs"]}
  assert conv_macs in macs and dot_macs in macs
  assert max(macs) <= conv_macs + dot_macs


def test_module_path_from_the_operation_metadata():
  op = {"op_name": "jit(<lambda>)/StereoAnyVideo/StereoAnyVideo.cascade/StereoAnyVideo.refine/"
                   "while/body/closed_call/StereoAnyVideo.one/StereoAnyVideo.step/update_block/"
                   "gru/convz1_0/conv_general_dilated"}
  assert op_profile.module_of(op, 2) == "update_block/gru"
  assert op_profile.module_of(op, 8) == "update_block/gru/convz1_0"
  assert op_profile.module_of({"op_name": ""}, 2) == "(no metadata)"


GPU_HLO = """HloModule jit_fn

ENTRY %main.10 (p0: f32[2,6,10,4], p1: f32[3,3,4,8], p2: f32[120,8], p3: f32[8,5]) -> f32[120,5] {
  %p0 = f32[2,6,10,4]{3,2,1,0} parameter(0)
  %p1 = f32[3,3,4,8]{3,2,1,0} parameter(1)
  %cudnn-conv.1 = (f32[2,6,10,8]{3,2,1,0}, u8[0]{0}) custom-call(f32[2,6,10,4]{3,2,1,0} %p0, f32[3,3,4,8]{3,2,1,0} %p1), window={size=3x3 pad=1_1x1_1}, dim_labels=b01f_01io->b01f, custom_call_target="__cudnn$convForward", metadata={op_name="jit(fn)/conv_general_dilated"}
  %p2 = f32[120,8]{1,0} parameter(2)
  %p3 = f32[8,5]{1,0} parameter(3)
  %cublas-gemm.1 = (f32[120,5]{1,0}, s8[4194304]{0}) custom-call(f32[120,8]{1,0} %p2, f32[8,5]{1,0} %p3), custom_call_target="__cublas$gemm", backend_config={"gemm_backend_config":{"dot_dimension_numbers":{"lhs_contracting_dimensions":["1"],"rhs_contracting_dimensions":["0"],"lhs_batch_dimensions":[],"rhs_batch_dimensions":[]}}}
  %other.1 = (f32[4]{0}, u8[0]{0}) custom-call(f32[120,8]{1,0} %p2, f32[8,5]{1,0} %p3), custom_call_target="SomethingElse"
  ROOT %get-tuple-element.1 = f32[120,5]{1,0} get-tuple-element((f32[120,5]{1,0}, s8[4194304]{0}) %cublas-gemm.1), index=0
}
"""


def test_multiply_adds_of_the_gpu_library_calls():
  """XLA:GPU turns convolutions and products into cuDNN / cuBLAS custom calls whose result
  is (output, workspace); their multiply-adds come from the first shape and the operands."""
  ops = op_profile.parse_hlo(GPU_HLO)
  assert ops["cudnn-conv.1"]["macs"] == 2 * 6 * 10 * 8 * (3 * 3 * 4)
  assert ops["cublas-gemm.1"]["macs"] == 120 * 5 * 8
  assert ops["other.1"]["macs"] == 0
  assert op_profile.kind_of("cudnn-conv.1", ops["cudnn-conv.1"]) == "cuDNN convolution"
  assert op_profile.kind_of("cublas-gemm.1", ops["cublas-gemm.1"]) == "cuBLAS product"


def _usage_error(main, argv, monkeypatch, capsys) -> str:
  """The standard error of a script's `main()` run with `sys.argv = argv`, which must end in
  a usage error (exit status 2)."""
  monkeypatch.setattr(sys, "argv", argv)
  with pytest.raises(SystemExit) as e:
    main()
  assert e.value.code == 2
  return capsys.readouterr().err


def _meta(kind, pid, name, tid=None):
  return {"ph": "M", "name": kind, "pid": pid, "tid": tid, "args": {"name": name}}


def test_operation_times_from_cpu_and_gpu_traces():
  cpu = [_meta("process_name", 1, "/host:CPU"),
         {"ph": "X", "pid": 1, "tid": 5, "dur": 3.0, "name": "f", "args": {"hlo_op": "fusion.1"}},
         {"ph": "X", "pid": 1, "tid": 6, "dur": 2.0, "name": "f", "args": {"hlo_op": "fusion.1"}},
         {"ph": "X", "pid": 1, "tid": 5, "dur": 9.0, "name": "python"}]
  assert op_profile.op_times(cpu) == {"fusion.1": (5.0, 2)}
  # GPU: host launch events and stream kernels carry hlo_op too; only "XLA Ops" counts.
  gpu = [_meta("process_name", 1, "/host:CPU"), _meta("process_name", 2, "/device:GPU:0"),
         _meta("thread_name", 2, "Stream #14", 1), _meta("thread_name", 2, "XLA Ops", 2),
         {"ph": "X", "pid": 1, "tid": 9, "dur": 1.0, "name": "cuLaunchKernel",
          "args": {"hlo_op": "fusion.1"}},
         {"ph": "X", "pid": 2, "tid": 1, "dur": 4.0, "name": "loop_fusion_kernel",
          "args": {"hlo_op": "fusion.1"}},
         {"ph": "X", "pid": 2, "tid": 2, "dur": 4.5, "name": "fusion.1", "args": {}},
         {"ph": "X", "pid": 2, "tid": 2, "dur": 7.0, "name": "cudnn-conv.1",
          "args": {"hlo_op": "cudnn-conv.1"}}]
  assert op_profile.op_times(gpu) == {"fusion.1": (4.5, 1), "cudnn-conv.1": (7.0, 1)}
  # without "XLA Ops" lines: the device's events only
  assert op_profile.op_times(gpu[:3] + gpu[4:6]) == {"fusion.1": (4.0, 1)}


def test_fft_correlation_equals_the_direct_convolution():
  """benchmarks/fft_conv.py's FFT form computes the same 'same'-padded correlation."""
  import fft_conv  # pylint: disable=import-outside-toplevel,import-error
  x = jax.random.normal(jax.random.PRNGKey(0), (2, 3, 11, 4))
  k = jax.random.normal(jax.random.PRNGKey(1), (1, 5, 4, 6))
  assert fft_conv.fft_size(11, 5) == 16  # >= 11 + 5 - 1, even
  want = fft_conv.direct(x, k)
  for got in (fft_conv.fft_correlate(x, k), fft_conv.dft_correlate(x, k)):
    assert got.shape == want.shape == (2, 3, 11, 6)
    assert float(jnp.abs(got - want).max()) < 1e-4 * float(jnp.abs(want).max())


def test_im2col_form_equals_the_direct_convolution():
  """benchmarks/conv_throughput.py's patch-matrix form is the same 'same'-padded conv."""
  import conv_throughput  # pylint: disable=import-outside-toplevel,import-error
  x = jax.random.normal(jax.random.PRNGKey(2), (2, 6, 9, 4))
  for kh, kw in ((3, 3), (1, 5), (5, 1)):
    k = jax.random.normal(jax.random.PRNGKey(kh), (kh, kw, 4, 7))
    pad = ((kh // 2, kh // 2), (kw // 2, kw // 2))
    want = conv_throughput.xla_conv(x, k, pad)
    got = conv_throughput.im2col_conv(x, k, pad)
    assert got.shape == want.shape == (2, 6, 9, 7)
    assert float(jnp.abs(got - want).max()) < 1e-5 * float(jnp.abs(want).max())
    # --dtype bfloat16: bfloat16 operands, float32 sums, in both forms
    xb, kb = x.astype(jnp.bfloat16), k.astype(jnp.bfloat16)
    for got in (conv_throughput.xla_conv(xb, kb, pad, jnp.float32),
                conv_throughput.im2col_conv(xb, kb, pad, jnp.float32)):
      assert got.dtype == jnp.float32
      assert float(jnp.abs(got - want).max()) < 2e-2 * float(jnp.abs(want).max())


def test_winograd_forms_equal_the_direct_convolution():
  """benchmarks/winograd_conv.py's F(m, 5) forms are the same 'same'-padded 5-tap
  convolution, for heights that are not multiples of m too."""
  import winograd_conv  # pylint: disable=import-outside-toplevel,import-error
  w = jax.random.normal(jax.random.PRNGKey(1), (5, 6, 3))
  for h in (8, 11):
    x = jax.random.normal(jax.random.PRNGKey(h), (2, h, 4, 6))
    want = winograd_conv.direct_h(x, w)
    for m in (2, 4, 6):
      for form in (winograd_conv.winograd_h, winograd_conv.winograd_h_sums):
        got = form(x, w, m)
        assert got.shape == want.shape == (2, h, 4, 3)
        assert float(jnp.abs(got - want).max()) < 1e-5 * float(jnp.abs(want).max()), (h, m)


def test_update_block_rewrites_compute_the_modules_values():
  """benchmarks/update_variants.py times rewrites of the same functions: each row of a
  group gives its first row's (the model module's) values."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  import update_variants  # pylint: disable=import-outside-toplevel,import-error
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel
  ub = init_variables(sav_jax.SAVConfig(), seed=0)["params"]["update_block"]
  keys = jax.random.split(jax.random.PRNGKey(0), 3)
  lead = (1, 3, 4, 5)
  h, x, n = (jax.random.normal(k, (*lead, c)) for k, c in zip(keys, (128, 256, 128)))
  rows = update_variants.variant_rows(ub, h, x, n, jnp.float32)
  rows += update_variants.motion_rows(ub["encoder"], h[..., :1], h, jnp.float32)
  ref, checked = {}, 0
  for label, fn, args, group in rows:
    out = np.asarray(fn(*args))
    channels = {"gru": 128, "flow": 2, "space": 256, "time": 256, "motion": 128}[group]
    assert out.shape == (*lead, channels), label
    if group in ref:
      np.testing.assert_allclose(out, ref[group], rtol=1e-4, atol=1e-4, err_msg=label)
      checked += 1
    ref.setdefault(group, out)
  assert checked == 11 and set(ref) == {"gru", "flow", "space", "time", "motion"}
  # The correlation rows in bfloat16 (the maps, the MLP) against the float32 model.
  f1, f2 = (jax.random.normal(k, (3, 4, 5, 128)) for k in keys[:2])
  disp = jax.random.uniform(keys[2], (3, 4, 5), maxval=3.0)
  corr = update_variants.corr_rows(
      init_variables(sav_jax.SAVConfig(), seed=0)["params"]["corr_mlp"], f1, f2, disp,
      jnp.bfloat16)
  assert [label for label, *_ in corr][0].endswith("(model)") and len(corr) == 3
  outs = [np.asarray(fn(*args)) for _, fn, args, _ in corr]
  # bfloat16 rounds to 2**-9 (0.2 %) of a value; through the maps and the MLP the rows land
  # within 0.6 % of the largest float32 value, so 2 % of it is the bound (10 % let a warp by
  # 0.97 times the disparity pass: 9.6 %).
  for out in outs[1:]:
    assert out.shape == outs[0].shape == (3, 4, 5, 128)
    np.testing.assert_allclose(out, outs[0], rtol=0, atol=0.02 * float(np.abs(outs[0]).max()))


def test_official_torch_script_checks_its_arguments_and_times_parts_per_scale(tmp_path, capsys):
  """benchmarks/official_torch.py (run where torch and an official checkout exist): its
  argument checks, the stand-ins for unused imports and the per-part timing need neither."""
  import types  # pylint: disable=import-outside-toplevel
  import pytest  # pylint: disable=import-outside-toplevel
  import official_torch  # pylint: disable=import-outside-toplevel,import-error
  mine = tmp_path / "mine.json"
  mine.write_text("precious")
  repo = tmp_path / "checkout"
  (repo / "models" / "core").mkdir(parents=True)
  for argv, message in ((["--repo", str(tmp_path)], "no models/core/stereoanyvideo.py"),
                        (["--repo", str(repo)], "no models/core/stereoanyvideo.py")):
    with pytest.raises(SystemExit):
      official_torch.parse_args(argv)
    assert message in capsys.readouterr().err
  (repo / "models" / "core" / "stereoanyvideo.py").write_text("")
  for extra, message in ((["--iters", "1"], "--iters must be >= 2"),
                         (["--json", str(mine)], "exists; pass --overwrite"),
                         (["--json", str(tmp_path)], "is a folder"),
                         (["--json", f"{tmp_path}/new/"], "ends in a slash"),
                         (["--json", str(tmp_path / "no" / "x.json")], "does not exist"),
                         (["--frames", "0"], "--frames must be >= 1 (got 0)"),
                         (["--height", "-32"], "--height must be >= 1 (got -32)"),
                         (["--batch", "0"], "--batch must be >= 1"),
                         (["--threads", "0"], "--threads must be >= 1"),
                         (["--overwrite"], "name one with --json")):
    with pytest.raises(SystemExit):
      official_torch.parse_args(["--repo", str(repo), *extra])
    assert message in capsys.readouterr().err
  assert mine.read_text() == "precious"
  assert official_torch.parse_args(["--repo", str(repo)]).repo == repo.resolve()
  # a --json file made during the run is kept without --overwrite (it was replaced)
  rec = tmp_path / "rec.json"

  def measure(_a):
    rec.write_text("the other run's")
    return dict(torch="x", threads=2, first_call_s=1.0, median_s=1.0, min_s=1.0,
                peak_rss_gb=1.0, parts_s=None)

  with pytest.MonkeyPatch.context() as mp:
    mp.setattr(official_torch, "measure", measure)
    mp.setattr(official_torch.importlib.util, "find_spec", lambda name: object())
    with pytest.raises(SystemExit) as e:
      official_torch.main(["--repo", str(repo), "--json", str(rec)])
  assert "was created during the run; not replaced" in str(e.value)
  assert rec.read_text() == "the other run's"

  official_torch._stand_in("json", loads=None)  # pylint: disable=protected-access
  assert sys.modules["json"].loads is not None  # a module that imports is left alone
  try:
    official_torch._stand_in("no_such_pkg.transforms", Compose=list)  # pylint: disable=protected-access
    import no_such_pkg.transforms as t  # pylint: disable=import-outside-toplevel,import-error
    assert t.Compose is list and sys.modules["no_such_pkg"].transforms is t
  finally:
    sys.modules.pop("no_such_pkg.transforms", None)
    sys.modules.pop("no_such_pkg", None)

  class Part:  # the hook API of torch.nn.Module, enough for time_parts
    def __init__(self):
      self.pre, self.post = [], []
    def register_forward_pre_hook(self, f):
      self.pre.append(f)
      return types.SimpleNamespace(remove=lambda: self.pre.remove(f))
    def register_forward_hook(self, f):
      self.post.append(f)
      return types.SimpleNamespace(remove=lambda: self.post.remove(f))
    def __call__(self, x):
      for f in self.pre:
        f(self, (x,))
      for f in self.post:
        f(self, (x,), x)

  parts = {name: Part() for name in official_torch.PARTS}
  model = types.SimpleNamespace(get_submodule=parts.__getitem__)
  small, large = types.SimpleNamespace(shape=(1, 8, 16)), types.SimpleNamespace(shape=(1, 32, 64))

  def call():
    for x in (small, large, large):
      parts["update_block.gru"](x)
    parts["depthnet"](large)

  got = official_torch.time_parts(model, call)
  assert {k: v["calls"] for k, v in got["parts"].items()} == {
      "update_block.gru @8x16": 1, "update_block.gru @32x64": 2, "depthnet @32x64": 1}
  assert all(v["s"] >= 0 for v in got["parts"].values()) and got["total"] >= 0
  assert all(not p.pre and not p.post for p in parts.values())  # hooks removed


def test_official_torch_json_records_the_cpu_model_that_bench_compares(tmp_path,
                                                                       monkeypatch):
  """The VMs all call themselves `vm`: without the CPU model, `sav-jax bench --compare` said
  nothing of an official baseline measured on another machine the same day."""
  import types  # pylint: disable=import-outside-toplevel
  import official_torch  # pylint: disable=import-outside-toplevel,import-error
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  fake = types.SimpleNamespace(
      from_numpy=lambda x: x, roll=lambda x, shift, dims: np.roll(x, shift, axis=dims),
      inference_mode=lambda: __import__("contextlib").nullcontext(),
      get_num_threads=lambda: 2, set_num_threads=lambda n: None, __version__="fake")
  monkeypatch.setitem(sys.modules, "torch", fake)
  monkeypatch.setattr(official_torch, "build_official_model",
                      lambda repo: lambda left, right, iters, test_mode: left[:, :, :1])
  a = types.SimpleNamespace(threads=None, repo=tmp_path, batch=1, frames=2, height=16,
                            width=32, iters=2, repeats=1, by_module=False)
  res = official_torch.measure(a)
  assert res["cpu"] == bench.cpu_model()
  here = {"device": "cpu:cpu", "host": res["host"], "cpu": "another CPU"}
  assert "cpu another CPU here" in bench.machine_note(here, res)


def test_infer_memory_script_runs_the_streaming_infer(tmp_path, monkeypatch, capsys):
  """benchmarks/infer_memory.py's stand-in still fits `inference._run_window`: the command
  it measures writes every frame's disparity."""
  import numpy as np  # pylint: disable=import-outside-toplevel

  import infer_memory  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  # The script replaces the model with its stand-in; monkeypatch puts the model back after.
  monkeypatch.setattr(inference, "_run_window",
                      inference._run_window)  # pylint: disable=protected-access
  monkeypatch.setattr(sys, "argv", ["infer_memory.py", str(tmp_path), "--frames", "23",
                                    "--height", "16", "--width", "24"])
  infer_memory.main()
  assert "exit 0;" in capsys.readouterr().out
  (out,) = tmp_path.glob("out_*")
  # Window [0, 20) keeps frames 0-14 (local 0-14), window [10, 23) frames 15-22 (local 5-12).
  expected = list(range(1, 16)) + list(range(6, 14))
  assert [float(np.load(out / "disparity" / f"{i:05d}.npy")[0, 0]) for i in range(23)] == expected
  # DATA holds that video: another size is refused, not measured on the old frames
  monkeypatch.setattr(sys, "argv", ["infer_memory.py", str(tmp_path), "--frames", "25",
                                    "--height", "16", "--width", "24"])
  with pytest.raises(SystemExit):
    infer_memory.main()
  assert "holds 23 frames of (16, 24) from an earlier run, not 25" in capsys.readouterr().err


def test_compile_times_script_names_a_bad_clip_before_compiling(monkeypatch, capsys):
  import compile_times  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(compile_times, "measure", lambda *a: pytest.fail("measured"))
  for args, message in ((["--iters", "1"], "--iters must be >= 2"),
                        (["--frames", "99"], "--frames must be at most 32"),
                        (["--frames", "0"], "--frames must be >= 1"),
                        (["--height", "30"], "multiples of 16")):
    with pytest.raises(SystemExit):
      compile_times.main(args)
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("script", ["compile_options", "op_profile", "memory_projection",
                                    "stage_times"])
def test_clip_scripts_name_a_clip_the_model_refuses_before_running(script, monkeypatch,
                                                                   capsys):
  module = __import__(script)
  err = _usage_error(module.main, [f"{script}.py", "--iters", "1"], monkeypatch, capsys)
  assert "--iters must be >= 2 (got 1)" in err


def test_memory_projection_names_a_bad_frame_block_budget_in_one_line(monkeypatch, capsys):
  import memory_projection  # pylint: disable=import-outside-toplevel,import-error
  for value in ("0", "-5", "nan"):
    err = _usage_error(memory_projection.main, ["memory_projection.py", "--frame-block-mb",
                                                value], monkeypatch, capsys)
    assert "--frame-block-mb" in err and "must be a finite number > 0" in err, err


def test_bf16_audit_names_a_gradient_clip_the_model_refuses_before_running(monkeypatch,
                                                                          capsys):
  """--gradients' clip is checked before the forward rows (minutes), not refused by the
  model's trace after them."""
  import bf16_audit  # pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(bf16_audit, "make_weights_module", lambda *a: pytest.fail("ran"))
  for args, message in ((["--height", "40"], "multiples of 16"),
                        (["--frames", "0"], "--frames must be >= 1")):
    with pytest.raises(SystemExit) as e:
      bf16_audit.main(["--gradients", *args])
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_compile_times_script_compiles_what_predict_video_runs(capsys):
  """benchmarks/compile_times.py compiles predict_video's per-frame and window programs,
  leaves the cache and low-memory settings as they were, and refuses bad sizes."""
  import compile_times  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  from sav_jax import inference, runtime  # pylint: disable=import-outside-toplevel

  before = (jax.config.jax_compilation_cache_dir, runtime._low_memory_compile)  # pylint: disable=protected-access
  result = compile_times.main(["--frames", "1", "--height", "16", "--width", "32",
                               "--iters", "2"])
  assert (jax.config.jax_compilation_cache_dir, runtime._low_memory_compile) == before  # pylint: disable=protected-access
  assert list(result["compile_s"]) == ["frames", "window"]
  assert all(s > 0 for s in result["compile_s"].values()) and result["peak_rss_gb"] > 0
  assert "total" in capsys.readouterr().out
  # It compiled predict_video's two programs for this video (in inference's own cache, so
  # with the options inference gives each: tests/test_inference.py checks those).
  compiled = {(k[0], k[2]) for k in inference._COMPILED if k[3] == (1, 16, 32)}  # pylint: disable=protected-access
  assert ("window", 2) in compiled and "frames" in {kind for kind, _ in compiled}
  with pytest.raises(SystemExit):
    compile_times.main(["--height", "30"])
  assert "multiples of 16" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    compile_times.main(["--height", "32", "--width", "16"])
  assert "the width at least 32" in capsys.readouterr().err


def test_raft_flow_script_times_the_evaluators_flow(monkeypatch, capsys):
  """benchmarks/raft_flow.py builds RAFT from the test manifest's layout and times
  `raft_flow` at the size asked for (a size that needs padding)."""
  import raft_flow  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(sys, "argv", ["raft_flow.py", "--height", "130", "--width", "129",
                                    "--iters", "1", "--repeats", "1"])
  raft_flow.main()
  out = capsys.readouterr().out
  assert "sav-jax RAFT 130x129 iters=1 (cpu): first call " in out and "peak RSS" in out, out


def test_raft_flow_script_names_bad_options_before_running(tmp_path, monkeypatch, capsys):
  import raft_flow  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(raft_flow, "make_weights_module", lambda *a: pytest.fail("ran"))
  refused = lambda *args: _usage_error(raft_flow.main, ["raft_flow.py", *args],  # noqa: E731
                                       monkeypatch, capsys)
  assert "no third_party/RAFT/core/raft.py" in refused("--official", str(tmp_path))
  assert "--repeats must be >= 1, got 0" in refused("--repeats", "0")


@pytest.mark.parametrize("args, message", [
    (["--height", "-5"], "--frames, --height and --width must be >= 1, got 40 frames of -5x"),
    (["--frames", "0"], "must be >= 1, got 0 frames"), (["--iters", "1"], "--iters must be >= 2"),
    (["--devices", "two"], "--devices: devices must be a number")])
def test_predict_video_script_names_bad_options_before_running(args, message, monkeypatch,
                                                               capsys):
  import predict_video  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(predict_video, "init_variables", lambda *a, **k: pytest.fail("ran"))
  assert message in _usage_error(predict_video.main, ["predict_video.py", *args], monkeypatch,
                                 capsys)


def test_scripts_refuse_to_overwrite_a_results_json_before_running(tmp_path, monkeypatch,
                                                                   capsys):
  import precision_check  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  import train_step  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  mine = tmp_path / "mine.json"
  mine.write_text("precious")
  monkeypatch.setattr(train_step, "measure", lambda *a: pytest.fail("measured"))
  monkeypatch.setattr(precision_check, "measure", lambda *a: pytest.fail("measured"))
  for run in (lambda args: precision_check.main(args),
              lambda args: (monkeypatch.setattr(sys, "argv", ["train_step.py", *args]),
                            train_step.main())):
    for args, message in ((["--json", str(mine)], "exists; pass --overwrite"),
                          (["--json", str(tmp_path)], "is a folder"),
                          (["--json", f"{tmp_path}/new/"], "ends in a slash"),
                          (["--json", str(tmp_path / "no" / "r.json")], "does not exist"),
                          (["--overwrite"], "name one with --json")):
      with pytest.raises(SystemExit) as e:
        run(args)
      assert e.value.code == 2 and message in capsys.readouterr().err
  assert mine.read_text() == "precious"


def test_scripts_keep_a_results_json_made_during_the_run_without_overwrite(tmp_path,
                                                                         monkeypatch, capsys):
  """A file of the --json name made during the run (another run writing the same name) is
  kept without --overwrite, as `sav-jax bench` keeps it; it was silently replaced."""
  import precision_check  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  import train_step  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  rec = tmp_path / "rec.json"
  res = dict(device="cpu:cpu", devices=1, jax="x", batch=1, frames=2, height=32, width=64,
             iters=2, dtype="float32", remat=True, compile_s=1.0, trace_s=0.1, lower_s=0.1,
             xla_compile_s=0.8, median_s=0.5, min_s=0.5, samples_per_s=2.0, peak_rss_gb=1.0)

  def measure(*args, result):
    rec.write_text("the other run's")
    return dict(result) if isinstance(result, dict) else list(result)

  monkeypatch.setattr(train_step, "measure", lambda *a: measure(*a, result=res))
  monkeypatch.setattr(precision_check, "measure", lambda *a: measure(*a, result=[]))
  for main, argv in ((train_step.main, ["train_step.py", "--json", str(rec)]),
                     (precision_check.main, ["precision_check.py", "--json", str(rec)])):
    rec.unlink(missing_ok=True)
    err = _usage_error(main, argv, monkeypatch, capsys)
    assert "was created during the run; not replaced" in err and rec.read_text() == (
        "the other run's")


def test_train_step_script_names_a_bad_clip_or_microbatches_before_running(monkeypatch,
                                                                           capsys):
  """Sizes the model refuses were a JAX traceback from the trace, naming no flag."""
  import train_step  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(train_step, "measure", lambda *a: pytest.fail("measured"))
  for args, message in ((["--height", "17"], "--height/--width must be positive multiples"),
                        (["--iters", "1"], "--iters must be >= 2"),
                        (["--frames", "99"], "--frames must be at most 32"),
                        (["--batch", "0"], "--batch must be >= 1"),
                        (["--repeats", "0"], "--repeats must be >= 1"),
                        (["--batch", "3", "--microbatches", "2"], "does not divide"),
                        (["--overwrite"], "name one with --json")):
    assert message in _usage_error(train_step.main, ["train_step.py", *args], monkeypatch,
                                   capsys)
  # A batch the devices cannot share was JAX's IndivisibleError traceback from device_put.
  monkeypatch.setattr(jax, "device_count", lambda: 2)
  for args, message in ((["--batch", "1"], "--batch 1 is not divisible by the 2 devices"),
                        (["--batch", "2", "--microbatches", "2"], "parts of 1 is not divisible")):
    assert message in _usage_error(train_step.main, ["train_step.py", *args], monkeypatch,
                                   capsys)


def test_train_step_script_keeps_its_program_in_the_named_compilation_cache(
    tmp_path, monkeypatch, capsys, restore_cache_config):
  """`benchmarks/train_step.py --compile-cache DIR` (gpu_suite.sh's train and train_warm
  steps) turns the cache on in DIR before measuring; a file there is refused first."""
  import train_step  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  seen = []
  monkeypatch.setattr(train_step, "measure", lambda *a: seen.append(
      jax.config.jax_compilation_cache_dir) or pytest.fail("measured"))
  afile = tmp_path / "cache_file"
  afile.write_text("x")
  for args, code in (([str(afile)], 2), ([str(tmp_path / "cache")], None)):
    monkeypatch.setattr(sys, "argv", ["train_step.py", "--compile-cache", *args])
    with pytest.raises((SystemExit, pytest.fail.Exception)) as e:
      train_step.main()
    if code is not None:
      assert e.value.code == 2 and "exists and is not a folder" in capsys.readouterr().err
  assert seen == [str(tmp_path / "cache")] and (tmp_path / "cache").is_dir()
  # The JSON says whether the step was compiled into the cache or loaded from it (a rerun
  # into the same folder loads: its figures are then a warm run's).
  runs = iter([{"stored": 1}, {}])

  def fake_measure(cfg, repeats):
    for name in next(runs):
      (tmp_path / "cache" / f"entry{name}").write_text("program")
    return {k: 1.0 for k in ("compile_s", "trace_s", "lower_s", "xla_compile_s", "median_s",
                             "min_s", "samples_per_s")} | {
        "device": "cpu", "devices": 1, "jax": "x", "batch": 1, "frames": 5, "height": 8,
        "width": 8, "iters": 2, "dtype": "float32", "remat": True}

  monkeypatch.setattr(train_step, "measure", fake_measure)
  monkeypatch.setattr(train_step, "memory_lines", lambda res, batch: [])
  hits = []
  for name in ("cold", "warm"):
    out = tmp_path / f"{name}.json"
    monkeypatch.setattr(sys, "argv", ["train_step.py", "--compile-cache", str(tmp_path / "cache"),
                                      "--json", str(out)])
    train_step.main()
    hits.append(json.loads(out.read_text())["cache_hit"])
    assert json.loads(out.read_text())["repeats"] == 3  # the default: the median's sample size
  assert hits == [False, True]
  printed = capsys.readouterr().out
  assert f"stored in {tmp_path / 'cache'}" in printed and "loaded from the compilation cache" in printed
  # The folder JAX_COMPILATION_CACHE_DIR names (the script's default) is probed as well: a
  # load from it was reported as a compile.
  runs = iter([{}])
  monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "cache"))
  out = tmp_path / "env.json"
  monkeypatch.setattr(sys, "argv", ["train_step.py", "--json", str(out)])
  train_step.main()
  assert json.loads(out.read_text())["cache_hit"] is True
  assert "loaded from the compilation cache" in capsys.readouterr().out


def test_parity_sweep_script_checks_its_cases_and_builds_shifted_views(tmp_path, capsys):
  """benchmarks/parity_sweep.py (run where torch and an official checkout exist): its case
  list, its argument checks and its clips need neither."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  import parity_sweep  # pylint: disable=import-outside-toplevel,import-error
  cases = parity_sweep.parse_cases(parity_sweep.DEFAULT_CASES)
  assert ("uneven", "window", (1, 3, 71, 135), "smooth") in cases
  assert {kind for _, kind, _, _ in cases} == {"window", "fbt", "direct"}
  for bad in ("a=window:1x3x8", "a=fast:1x3x8x8:noise", "a=window:2x3x8x8:noise",
              "a=window:1x3x8x8:stripes", "a:window:1x3x8x8:noise"):
    with pytest.raises(SystemExit, match="--cases"):
      parity_sweep.parse_cases(bad)
  mine = tmp_path / "mine.json"
  mine.write_text("precious")
  for extra, message in ((["--iters", "1"], "--iters must be >= 2"),
                         (["--json", str(mine)], "exists; pass --overwrite")):
    with pytest.raises(SystemExit):
      parity_sweep.parse_args(["--repo", str(tmp_path), *extra])
    assert message in capsys.readouterr().err
  assert mine.read_text() == "precious"
  for kind, shift in (("noise", 3), ("smooth", 5)):  # right(x) = left(x + shift)
    left, right = parity_sweep.clip(2, 8, 20, kind)
    assert left.shape == right.shape == (2, 8, 20, 3) and left.dtype == np.float32
    np.testing.assert_array_equal(right[:, :, :20 - shift], left[:, :, shift:])
    assert 0 <= left.min() and left.max() <= 255
  left, _ = parity_sweep.batch((2, 1, 8, 20), "noise")
  assert left.shape == (2, 1, 8, 20, 3) and not np.array_equal(left[0], left[1])
  # rows: a clip of <= 5 frames has none after the official [:-5] trimming, on both sides
  # (the table's reduction failed on the empty arrays)
  row = parity_sweep.compare_row("t3", (1, 3, 8, 20), "fbt", np.zeros((0, 8, 20)),
                                 np.zeros((0, 8, 20)))
  assert row["max_px"] == 0 and "no frames" in row["what"]
  row = parity_sweep.compare_row("a", (1, 1, 2, 2), "x", np.ones((1, 2, 2)), np.full((1, 2, 2), 3))
  assert (row["max_px"], row["mean_px"], row["official_max_px"]) == (2, 2, 3)
  with pytest.raises(ValueError, match=r"a \(x\): sav-jax gives shape \(1, 2\), the official"):
    parity_sweep.compare_row("a", (1,), "x", np.ones((1, 2)), np.ones((2, 2)))


def test_official_side_scripts_name_a_missing_checkout_torch_or_failure_in_one_line(
    tmp_path, monkeypatch):
  """gradient_check.py / parity_sweep.py: a wrong --repo, --fixtures or --torch-interpreter,
  an interpreter without torch and a failing official side end in one line, not a traceback;
  official_torch.py without torch too."""
  import argparse  # pylint: disable=import-outside-toplevel
  import gradient_check  # pylint: disable=import-outside-toplevel,import-error
  import official_torch  # pylint: disable=import-outside-toplevel,import-error
  repo = tmp_path / "checkout"
  (repo / "models" / "core").mkdir(parents=True)
  (repo / "models" / "core" / "stereoanyvideo.py").write_text("")
  fixtures = tmp_path / "fixtures"
  fixtures.mkdir()
  (fixtures / "make_weights.py").write_text("")
  fake = tmp_path / "py"  # "has torch", then the official side fails
  fake.write_text('#!/bin/sh\n[ "$1" = -c ] && exit 0\nexit 3\n')
  fake.chmod(0o755)
  no_torch = tmp_path / "py0"
  no_torch.write_text("#!/bin/sh\nexit 1\n")
  no_torch.chmod(0o755)
  for repo_, fix, interp, message in (
      (tmp_path, fixtures, fake, "no models/core/stereoanyvideo.py"),
      (repo, tmp_path, fake, "no make_weights.py"),
      (repo, fixtures, tmp_path / "none", "no such program"),
      (repo, fixtures, no_torch, "torch is not installed there"),
      (repo, fixtures, fake, "failed with exit status 3")):
    a = argparse.Namespace(repo=str(repo_), fixtures=str(fix), torch_interpreter=str(interp))
    with pytest.raises(SystemExit, match=message):
      gradient_check.official_outputs(a, [], "script.py")
  monkeypatch.setattr(official_torch.importlib.util, "find_spec", lambda name: None)
  with pytest.raises(SystemExit, match="torch is not installed"):
    official_torch.main(["--repo", str(repo)])


def test_input_pipeline_script_writes_flyingthings_and_times_the_training_stream(
    tmp_path, monkeypatch, capsys):
  """`benchmarks/input_pipeline.py`: the set it writes is read back by the FlyingThings3D
  reader as written (PNG frames, PFM disparities, invalid pixels 0), and the training stream
  it times yields batches of the asked shape."""
  import cv2  # pylint: disable=import-outside-toplevel
  import input_pipeline  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
  from sav_jax.data.synthetic import SyntheticConfig, generate_clip  # pylint: disable=import-outside-toplevel
  nbytes = input_pipeline.write_flyingthings(tmp_path / "set", 2, 3, size=(40, 72))
  seqs = registry.get_sequences("flyingthings3d", tmp_path / "set", "train")
  assert [len(s) for s in seqs] == [3, 3]
  seq = seqs[0]
  clip = generate_clip(SyntheticConfig(frames=3, height=40, width=72, seed=0), index=0)
  for t in range(3):
    frame = seq[t]
    np.testing.assert_array_equal(frame["left"], clip["left"][t])
    np.testing.assert_array_equal(frame["right"], clip["right"][t])
    np.testing.assert_array_equal(frame["disparity"],
                                  np.where(clip["valid"][t], clip["disparity"][t], 0))
  assert nbytes > 0 and cv2.imread(str(next((tmp_path / "set").rglob("*.png")))) is not None

  out = tmp_path / "r.json"
  monkeypatch.setattr(input_pipeline, "SCENEFLOW_SIZE", (48, 80))
  monkeypatch.setattr(sys, "argv", [
      "input_pipeline.py", "--sequences", "1", "--sequence-frames", "3", "--frames", "2",
      "--crop", "32", "64", "--batch", "2", "--warmup", "1", "--batches", "1", "--clips", "1",
      "--num-threads", "1", "--json", str(out)])
  input_pipeline.main()
  res = json.loads(out.read_text())
  # 3 frames, clips of 2: one start, forward and time-reversed (the official sampling).
  assert res["training_clips"] == 2 and res["written"] == "1 x 3 frames at 48x80"
  assert res["clips_per_s"] > 0 and res["read_s"] > 0 and res["augment_s"] > 0
  assert res["cores_per_accelerator"] == pytest.approx(3.0 * (res["read_s"] + res["augment_s"]))
  assert "clips/s over 1 batches after 1" in capsys.readouterr().out
  assert "more than --sequence-frames 10" in _usage_error(
      input_pipeline.main, ["input_pipeline.py", "--frames", "11"], monkeypatch, capsys)


@pytest.mark.parametrize("args,message", [
    (["--root", "{tmp}/missing"], "dataset root not found: "),
    (["--dataset", "sceneflw"], "unknown dataset 'sceneflw'"),
    (["--dataset", "sintel_final"], "sintel_final has no official training clips"),
])
def test_input_pipeline_script_names_a_wrong_root_or_dataset_in_one_line(
    tmp_path, monkeypatch, capsys, args, message):
  """`--root`/`--dataset` that give no training clips: an argparse error, not a traceback."""
  import input_pipeline  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  args = [x.format(tmp=tmp_path) for x in args]
  root = [] if "--root" in args else ["--root", str(tmp_path)]
  err = _usage_error(input_pipeline.main, ["input_pipeline.py", *root, *args], monkeypatch,
                     capsys)
  assert message in err and "Traceback" not in err


def test_gru_conv_forms_agree():
  """benchmarks/gru_conv.py times both forms of the GRU; they compute the same update."""
  import gru_conv  # pylint: disable=import-outside-toplevel,import-error
  times, diff = gru_conv.gru_times(2, 4, 8, repeats=1)
  assert set(times) == {"direct", "dft"} and min(times.values()) > 0
  assert diff < 1e-5


def test_infer_throughput_script_checks_its_json_path_before_the_run(tmp_path, monkeypatch,
                                                                    capsys):
  """A --json in a missing folder is named before anything runs, not a traceback after."""
  import infer_throughput  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  monkeypatch.setattr(sys, "argv", ["infer_throughput.py", str(tmp_path / "d"), "--json",
                                    str(tmp_path / "no" / "r.jsonl")])
  with pytest.raises(SystemExit):
    infer_throughput.main()
  assert "does not exist" in capsys.readouterr().err and not (tmp_path / "d").exists()


def test_infer_throughput_script_stops_with_infers_error_and_records_nothing(
    tmp_path, monkeypatch, capsys):
  """An infer that fails (here a bad --format) ends the script with its exit status and its
  one-line error: no traceback, no row of made-up frames/s in --json."""
  import infer_throughput  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import infer  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(inference, "_run_window",
                      inference._run_window)  # pylint: disable=protected-access
  monkeypatch.setattr(infer, "load_checkpoint", infer.load_checkpoint)
  argv = ["infer_throughput.py", str(tmp_path / "d"), "--frames", "2", "--height", "16",
          "--width", "24", "--format", "bogus", "--json", str(tmp_path / "r.jsonl")]
  assert "unknown --format" in _usage_error(infer_throughput.main, argv, monkeypatch, capsys)
  assert not (tmp_path / "r.jsonl").exists() and not list((tmp_path / "d").glob("out_*"))


def test_infer_throughput_script_runs_infer_with_its_stand_in(tmp_path, monkeypatch, capsys):
  """benchmarks/infer_throughput.py's stand-in still fits `inference._run_window` and the
  command it times writes every frame."""
  import json  # pylint: disable=import-outside-toplevel

  import infer_throughput  # noqa: E402  pylint: disable=import-outside-toplevel,import-error
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import infer  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(inference, "_run_window",
                      inference._run_window)  # pylint: disable=protected-access
  monkeypatch.setattr(infer, "load_checkpoint", infer.load_checkpoint)
  monkeypatch.setattr(sys, "argv", ["infer_throughput.py", str(tmp_path / "d"), "--frames", "23",
                                    "--height", "16", "--width", "24", "--format", "png16,npy",
                                    "--calib", "--keep", "--profile", "--json",
                                    str(tmp_path / "r.jsonl")])
  infer_throughput.main()
  assert "exit 0;" in capsys.readouterr().out
  (out,) = (tmp_path / "d").glob("out_*")
  assert len(list((out / "disparity").glob("*.png"))) == 23
  assert len(list((out / "pointclouds").glob("*.ply"))) == 23
  (row,) = [json.loads(line) for line in (tmp_path / "r.jsonl").read_text().splitlines()]
  assert row["frames"] == 23 and row["frames_per_second"] > 0 and "stages_s" in row


def test_startup_times_script_takes_medians_of_fresh_processes(monkeypatch, capsys):
  """benchmarks/startup_times.py: each run a fresh `python -c` process measuring the import,
  the shapes' trace and two traces; the figures are medians; a failed process is named with
  its error, not a traceback of the parent."""
  import subprocess  # pylint: disable=import-outside-toplevel
  import types  # pylint: disable=import-outside-toplevel
  import startup_times  # pylint: disable=import-outside-toplevel,import-error
  runs = iter([1.0, 3.0, 2.0])

  def fake_run(cmd, **kwargs):
    assert cmd[:2] == [sys.executable, "-c"] and "abstract_variables" in cmd[2]
    v = next(runs)
    return types.SimpleNamespace(returncode=0, stderr="", stdout=json.dumps(
        {"import_jax": v, "shapes": 2 * v, "forward_trace": 3 * v, "grad_trace": 4 * v,
         "ml_dtypes": "0.6.0", "jax": "x", "flax": "y"}) + "\n")

  monkeypatch.setattr(subprocess, "run", fake_run)
  assert startup_times.main(["--runs", "3", "--json"]) == 0
  res = json.loads(capsys.readouterr().out)
  assert (res["import_jax"], res["shapes"], res["grad_trace"], res["runs"]) == (2.0, 4.0, 8.0, 3)
  monkeypatch.setattr(subprocess, "run", lambda cmd, **k: types.SimpleNamespace(
      returncode=1, stdout="", stderr="Traceback ...\nImportError: no jax"))
  with pytest.raises(SystemExit, match="the measuring process failed:\nTraceback (?s:.*)no jax"):
    startup_times.main([])
  with pytest.raises(SystemExit):
    startup_times.main(["--runs", "0"])
  assert "--runs must be >= 1, got 0" in capsys.readouterr().err
