"""bfloat16 mode: the parts README promises stay float32, pinned on the traced program."""

import collections
import itertools

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax


def _dataflow(jaxpr):
  """Dataflow graph of `jaxpr` with every called jaxpr inlined (pjit, custom_jvp/vjp calls,
  cond branches, scans with their loop edges): `(succ, pred, aval, prim, root, in_scan)`
  over nodes `(instance, var)` of the jaxprs' instances; `prim[node]` is the primitive that
  wrote it ("" for inputs and the identity edges in and out of a call), `in_scan` the
  instances inside a scan body. Opaque primitives join every input to every output."""
  succ, pred = collections.defaultdict(set), collections.defaultdict(set)
  aval, prim = {}, {}
  instances = itertools.count()
  in_scan = set()

  def node(ctx, v, p=""):
    key = (ctx, v)
    aval[key] = v.aval
    prim.setdefault(key, p)
    return key

  def edge(a, b):
    succ[a].add(b)
    pred[b].add(a)

  def inline(j, ins, outs, looped):  # the outer nodes `ins` feed j.invars, j.outvars `outs`
    ctx = next(instances)
    if looped:
      in_scan.add(ctx)
    for v, outer in zip(j.invars, ins):
      if outer is not None:
        edge(outer, node(ctx, v))
    for v in j.constvars:
      node(ctx, v)
    build(j, ctx)
    inner = [None if isinstance(v, jax.extend.core.Literal) else node(ctx, v) for v in j.outvars]
    for i, o in zip(inner, outs):
      if i is not None:
        edge(i, o)
    return ctx, inner

  def build(j, ctx):
    for eqn in j.eqns:
      name = eqn.primitive.name
      ins = [None if isinstance(v, jax.extend.core.Literal) else node(ctx, v) for v in eqn.invars]
      outs = [node(ctx, v, name) for v in eqn.outvars]
      subs = {k: (v.jaxpr if hasattr(v, "jaxpr") else v) for k, v in eqn.params.items()
              if isinstance(v, (jax.extend.core.Jaxpr, jax.extend.core.ClosedJaxpr))}
      if name == "scan":
        body = subs["jaxpr"]
        n_carry, n_consts = eqn.params["num_carry"], eqn.params["num_consts"]
        inner_ctx, inner_outs = inline(body, ins, outs, True)
        for k in range(n_carry):  # loop edges: iteration i + 1 reads iteration i's carry
          if inner_outs[k] is not None:
            edge(inner_outs[k], node(inner_ctx, body.invars[n_consts + k]))
      elif name == "cond":
        for branch in eqn.params["branches"]:
          inline(branch.jaxpr, ins[1:], outs, ctx in in_scan)
        for o in outs:
          edge(ins[0], o)
      elif (len(subs) == 1 and len(next(iter(subs.values())).invars) == len(ins)
            and len(next(iter(subs.values())).outvars) == len(outs)):
        inline(next(iter(subs.values())), ins, outs, ctx in in_scan)
      else:
        assert not subs, f"unexpected sub-jaxprs in {name}: {sorted(subs)}"
        for i in ins:
          for o in outs:
            if i is not None:
              edge(i, o)

  root = next(instances)
  for v in itertools.chain(jaxpr.invars, jaxpr.constvars):
    node(root, v)
  build(jaxpr, root)
  return succ, pred, aval, prim, root, in_scan


def _reach(edges, start, keep=lambda n: True, stop=lambda n: False):
  """Nodes reachable from `start` along `edges` (start included), through nodes that `keep`
  accepts, not continuing past nodes where `stop` holds (those are included)."""
  seen, todo = set(start), list(start)
  while todo:
    n = todo.pop()
    if stop(n) and n not in start:
      continue
    for m in edges.get(n, ()):
      if m not in seen and keep(m):
        seen.add(m)
        todo.append(m)
  return seen


def _not_float32(nodes, aval):
  """The floating nodes of `nodes` that are not float32, as readable strings."""
  return sorted({f"{aval[n].dtype.name}{list(aval[n].shape)}" for n in nodes
                 if jnp.issubdtype(aval[n].dtype, jnp.floating) and aval[n].dtype != jnp.float32})


B, T, H, W, ITERS = 1, 2, 32, 64, 2


@pytest.fixture(scope="module")
def bf16_cascade():
  """The bfloat16 cascade (1/16, 1/8, 1/4 refinement scans) from float32 features, traced at
  B=1 T=2 32x64 iters=2 with every step's prediction kept: `(variables, jaxpr)`. Tracing
  only (~7 s on 2 CPU cores, the abstract init included), nothing is compiled."""
  model = sav_jax.StereoAnyVideo(sav_jax.SAVConfig(dtype="bfloat16"))
  feat = jax.ShapeDtypeStruct((B, T, H // 4, W // 4, 128), jnp.float32)
  kw = {"size": (H, W), "iters": ITERS, "final_only": False, "method": "cascade"}
  variables = jax.eval_shape(lambda *a: model.init(jax.random.key(0), *a, **kw), feat, feat, feat)
  closed = jax.make_jaxpr(lambda v, *a: model.apply(v, *a, **kw))(variables, feat, feat, feat)
  return variables, closed.jaxpr


@pytest.fixture(scope="module")
def bf16_refine_steps(bf16_cascade):
  """For each refinement scan of `bf16_cascade`: its body's dataflow graph and the roles of
  the body's inputs and outputs."""
  variables, top = bf16_cascade
  params = {v: "/".join(str(k.key) for k in path) for (path, _), v in
            zip(jax.tree_util.tree_flatten_with_path(variables)[0], top.invars)}
  steps = []
  for eqn in top.eqns:
    if eqn.primitive.name != "scan":
      continue
    body = eqn.params["jaxpr"].jaxpr
    n_consts, n_carry = eqn.params["num_consts"], eqn.params["num_carry"]
    succ, pred, aval, prim, root, _ = _dataflow(body)
    node = lambda v, root=root: (root, v)  # noqa: E731
    carry_in, carry_out = body.invars[n_consts:n_consts + n_carry], body.outvars[:n_carry]
    (k,) = [k for k, v in enumerate(carry_in) if v.aval.ndim == 5 and v.aval.shape[-1] == 1]
    h, w = carry_in[k].aval.shape[2:4]
    consts = {params.get(outer): node(inner) for outer, inner in
              zip(eqn.invars[:n_consts], body.invars[:n_consts])}
    steps.append({
        "graph": (succ, pred, aval, prim), "hw": (h, w),
        "flow_in": node(carry_in[k]), "flow_out": node(carry_out[k]),
        # fmap1, fmap2 (and the context input, which the correlation does not read)
        "maps": [node(v) for v in body.invars[:n_consts]
                 if v.aval.shape == (B, T, h, w, 128) and v.aval.dtype == jnp.float32],
        "fc1": consts["params/corr_mlp/fc1/kernel"], "fc2": consts["params/corr_mlp/fc2/kernel"],
        "up": [node(v) for v in body.outvars[n_carry:]
               if v.aval.shape[-4:] == (T, 4 * h, 4 * w, 1)],
    })
  assert [s["hw"] for s in steps] == [(H // 16, W // 16), (H // 8, W // 8), (H // 4, W // 4)]
  return steps


def _first_dots(step, kernel):
  """Outputs of the first dot_generals downstream of a parameter node (its dense layer)."""
  succ, _, _, prim = step["graph"]
  reached = _reach(succ, [kernel], stop=lambda n: prim[n] == "dot_general")
  return [n for n in reached if prim[n] == "dot_general"]


def test_bfloat16_correlation_and_corr_mlp_stay_float32(bf16_refine_steps):
  """Every value on a path from the feature maps or the disparity to corr_mlp's output
  (warp, window correlation, fc1, GELU, fc2) is float32: no rounding to bfloat16 of the
  correlation volume before, or inside, corr_mlp."""
  for step in bf16_refine_steps:
    succ, pred, aval, prim = step["graph"]
    fc1, fc2 = _first_dots(step, step["fc1"]), _first_dots(step, step["fc2"])
    assert len(fc1) == 1 and len(fc2) == 1
    assert len(step["maps"]) == 3  # fmap1, fmap2, context input
    path = (_reach(succ, step["maps"] + [step["flow_in"]]) & _reach(pred, fc2))
    assert fc1[0] in path and any(aval[n].shape[-1:] == (4 * 81,) for n in path)  # the volume
    assert not _not_float32(path, aval), (step["hw"], _not_float32(path, aval))


def test_bfloat16_disparity_accumulator_stays_float32(bf16_refine_steps):
  """The scan's disparity carry is float32 and so is every value between the carry in and
  the carry out that has the disparity's size (`flow + delta`: no bfloat16 rounding of the
  sum or of the flow before it; `delta` itself comes from the bfloat16 flow head)."""
  for step in bf16_refine_steps:
    succ, pred, aval, _ = step["graph"]
    size = lambda n, aval=aval: int(np.prod(aval[n].shape))  # noqa: E731
    n = size(step["flow_in"])
    same = lambda m, n=n, size=size: size(m) == n  # noqa: E731
    chain = (_reach(succ, [step["flow_in"]], keep=same)
             & _reach(pred, [step["flow_out"]], keep=same))
    assert step["flow_in"] in chain and step["flow_out"] in chain
    assert aval[step["flow_in"]].dtype == aval[step["flow_out"]].dtype == jnp.float32
    assert not _not_float32(chain, aval), (step["hw"], _not_float32(chain, aval))


def test_bfloat16_convex_upsampling_stays_float32(bf16_refine_steps):
  """The step's upsampled disparity is computed in float32 from the float32 disparity
  (x4, the 3x3x3 neighbours, the weighted sum) and from the mask head's logits: everything
  after the bfloat16 mask convolution (27*16 channels), softmax included, is float32."""
  for step in bf16_refine_steps:
    succ, pred, aval, prim = step["graph"]
    (up,) = step["up"]
    assert aval[up].dtype == jnp.float32
    before_up = _reach(pred, [up])
    flow_path = _reach(succ, [step["flow_out"]]) & before_up
    assert any(prim[n] == "dot_general" for n in flow_path)  # the weighted sum
    assert not _not_float32(flow_path, aval), (step["hw"], _not_float32(flow_path, aval))
    logits = [n for n in before_up
              if aval[n].shape[-1:] == (27 * 16,) and aval[n].dtype == jnp.bfloat16]
    assert logits  # the mask head computes in bfloat16
    mask_path = (_reach(succ, logits) - set(logits)) & before_up
    assert any(prim[n] == "exp" for n in mask_path)  # the softmax
    assert not _not_float32(mask_path, aval), (step["hw"], _not_float32(mask_path, aval))


def test_bfloat16_update_block_attention_softmax_stays_float32(bf16_refine_steps):
  """The update block's attention over time: the softmax (every `exp` of the step but the
  upsampling's) and its logits back to their product are float32, the product taking
  bfloat16 operands into a float32 result."""
  for step in bf16_refine_steps:
    succ, pred, aval, prim = step["graph"]
    (up,) = step["up"]
    before_up = _reach(pred, [up])
    logits = [n for n in before_up
              if aval[n].shape[-1:] == (27 * 16,) and aval[n].dtype == jnp.bfloat16]
    upsampling = _reach(succ, logits)
    exps = [n for n in aval if prim[n] == "exp" and n not in upsampling]
    assert exps
    for e in exps:
      back = _reach(pred, [e], stop=lambda n: prim[n] in ("dot_general", "conv_general_dilated"))
      dots = [n for n in back if prim[n] == "dot_general"]
      assert dots and not any(prim[n] == "conv_general_dilated" for n in back)
      assert not _not_float32(back, aval), (step["hw"], _not_float32(back, aval))
      for d in dots:  # bfloat16 operands (compute dtype) into float32 logits
        assert all(aval[p].dtype == jnp.bfloat16 for p in pred[d]), step["hw"]


def test_bfloat16_disparities_between_and_after_the_scans_stay_float32(bf16_cascade):
  """Outside the scans: each scale's upsampled disparities, the hand-over to the next scale
  (bilinear resize, rescaling) and the full-resolution predictions are float32 all the way."""
  _, top = bf16_cascade
  succ, pred, aval, _, root, in_scan = _dataflow(top)
  scans = [e for e in top.eqns if e.primitive.name == "scan"]
  flow_shape = lambda v: v.aval.ndim == 5 and v.aval.shape[-1] == 1  # noqa: E731
  ups = [(root, e.outvars[e.params["num_carry"]]) for e in scans]  # [iters, B, T, 4h, 4w, 1]
  inits = [(root, next(v for v in e.invars[e.params["num_consts"]:] if flow_shape(v)))
           for e in scans]
  (out,) = [(root, v) for v in top.outvars]
  assert [aval[u].shape[-3:-1] for u in ups] == [(H // 4, W // 4), (H // 2, W // 2), (H, W)]
  top_level = lambda n: n[0] not in in_scan  # noqa: E731  (paths that do not enter a scan)
  for k, up in enumerate(ups):
    after = _reach(succ, [up], keep=top_level)
    paths = after & _reach(pred, [out], keep=top_level)
    if k + 1 < len(ups):
      paths |= after & _reach(pred, [inits[k + 1]], keep=top_level)
      assert inits[k + 1] in paths
    assert out in paths and not _not_float32(paths, aval), (k, _not_float32(paths, aval))


def _equations(jaxpr):
  """Every equation of `jaxpr` and of the jaxprs its equations call (scan and cond bodies,
  pjit, custom_vjp and remat calls), recursively."""
  for eqn in jaxpr.eqns:
    yield eqn
    for value in eqn.params.values():
      for sub in value if isinstance(value, (list, tuple)) else [value]:
        if isinstance(sub, jax.extend.core.ClosedJaxpr):
          yield from _equations(sub.jaxpr)
        elif isinstance(sub, jax.extend.core.Jaxpr):
          yield from _equations(sub)


def test_bfloat16_training_gradient_sums_in_float32():
  """The bfloat16 training gradient (every trainable parameter, all predictions) has no sum
  of more than 32 bfloat16 terms: the biases' gradients (sums of the output's cotangent over
  every position, B*T*h*w terms) are summed in float32 (`layers.add_bias`). Summed in
  bfloat16 they were 85 reductions of 64-2048 terms at this tiny shape, and XLA:CPU's stall at
  a few hundred times a term made them ~10x too small at 8192 positions
  (tests/model/test_layers.py). What remains are the linear attention's normalisers over
  a head's 32 channels and its 8 heads (a few bfloat16 steps). Traced, not compiled."""
  cfg = sav_jax.SAVConfig(dtype="bfloat16")
  model = sav_jax.StereoAnyVideo(cfg)
  params = sav_jax.model.init.abstract_variables(cfg)["params"]
  frames = jax.ShapeDtypeStruct((B, T, H, W, 3), jnp.float32)

  def loss(p, left, right):
    return jnp.mean(model.apply({"params": p}, left, right, iters=ITERS).disparities)

  jaxpr = jax.make_jaxpr(jax.grad(loss))(params, frames, frames).jaxpr
  sums = [(int(np.prod([e.invars[0].aval.shape[a] for a in e.params["axes"]])),
           str(e.invars[0].aval.shape)) for e in _equations(jaxpr)
          if e.primitive.name == "reduce_sum" and e.invars[0].aval.dtype == jnp.bfloat16]
  assert sums  # the program does compute in bfloat16 (the attention's normalisers)
  assert max(sums)[0] <= 32, sorted(s for s in sums if s[0] > 32)[-5:]
