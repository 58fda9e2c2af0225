"""Tests for sav_jax.convert.torch_io / pickle_reader: safe torch checkpoint reading and writing."""

import collections
import io
import json
import logging
import os
import pickle
import pickletools
import re
import struct
import sys
import types
import zipfile

import numpy as np
import pytest

from sav_jax.convert import pickle_reader
from sav_jax.convert import torch_io
from sav_jax.convert.torch_io import CheckpointError

TORCH_FILES = ("plain_state_dict.pth", "sav_subset_zip.pth", "sav_subset_legacy.pth")


# --------------------------------------------------------------------------------------------
# The real torch-written fixtures.


@pytest.fixture(scope="module")
def torch_dir(fixtures_dir):
  return fixtures_dir / "torch_files"


@pytest.fixture(scope="module")
def expected(torch_dir):
  with np.load(torch_dir / "expected.npz") as data:
    out = collections.defaultdict(dict)
    for name in data.files:
      fname, key = name.split(":", 1)
      out[fname][key] = data[name]
  return out


@pytest.mark.parametrize("fname", TORCH_FILES)
def test_real_torch_files_match_expected(torch_dir, expected, fname):
  sd = torch_io.load_state_dict(torch_dir / fname)
  want = {k[len("module."):] if k.startswith("module.") else k: v
          for k, v in expected[fname].items()}
  assert list(sd) == list(want)
  for k, v in want.items():
    assert sd[k].dtype == v.dtype, k
    assert sd[k].shape == v.shape, k
    np.testing.assert_array_equal(sd[k], v, err_msg=k)
    assert sd[k].flags.c_contiguous and sd[k].flags.writeable, k


@pytest.mark.parametrize("fname", ["sav_subset_zip.pth", "sav_subset_legacy.pth"])
def test_real_training_checkpoint_object(torch_dir, fname):
  obj = torch_io.load_checkpoint_object(torch_dir / fname)
  assert set(obj) == {"model", "optimizer", "epoch"}
  assert obj["optimizer"] == {"step": 3} and obj["epoch"] == 7
  model = obj["model"]
  assert all(k.startswith("module.") for k in model)
  # dtypes of the fixture: float32, float16, bfloat16 (-> float32), float64.
  assert model["module.corr_mlp.fc1.bias"].dtype == np.float16
  assert model["module.update_block.mask3d.2.weight"].dtype == np.float32
  assert model["module.fnet.conv1.weight"].dtype == np.float64
  # view_a and view_b share one storage; the arrays must be independent copies.
  model["module.view_a"][...] = 0
  assert np.abs(model["module.view_b"]).sum() > 0


def test_real_zip_and_legacy_agree(torch_dir):
  a = torch_io.load_state_dict(torch_dir / "sav_subset_zip.pth")
  b = torch_io.load_state_dict(torch_dir / "sav_subset_legacy.pth")
  assert a.keys() == b.keys()
  for k in a:
    np.testing.assert_array_equal(a[k], b[k])


def test_real_plain_state_dict_scalars(torch_dir):
  sd = torch_io.load_state_dict(torch_dir / "plain_state_dict.pth")
  assert sd["norm.num_batches_tracked"].shape == () and sd["norm.num_batches_tracked"] == 12
  assert sd["norm.num_batches_tracked"].dtype == np.int64
  assert sd["scalar"].shape == () and sd["scalar"] == 1.5


# --------------------------------------------------------------------------------------------
# A minimal torch-format writer (fake torch modules so the stdlib pickler emits the same
# GLOBALs as torch.save), to cover every dtype, views, v3 tensors, big-endian files, ...

_STORAGE_NAMES = {
    "float64": "DoubleStorage", "float32": "FloatStorage", "float16": "HalfStorage",
    "bfloat16": "BFloat16Storage", "int64": "LongStorage", "int32": "IntStorage",
    "int16": "ShortStorage", "int8": "CharStorage", "uint8": "ByteStorage",
    "bool": "BoolStorage",
}


class _FakeDType:
  """Pickles as `GLOBAL torch <name>`, like a torch.dtype."""

  __module__ = "torch"

  def __init__(self, name):
    self.name = name

  def __reduce__(self):
    return self.name


def _fake_function(module, name):
  def fn(*args):
    del args
  fn.__module__, fn.__qualname__, fn.__name__ = module, name, name
  return fn


@pytest.fixture
def fake_torch(monkeypatch):
  """Installs fake `torch` modules (only for pickling in the test) and returns `torch`."""
  torch = types.ModuleType("torch")
  utils = types.ModuleType("torch._utils")
  tensor_mod = types.ModuleType("torch._tensor")
  nn = types.ModuleType("torch.nn")
  param_mod = types.ModuleType("torch.nn.parameter")
  for fname in ("_rebuild_tensor", "_rebuild_tensor_v2", "_rebuild_tensor_v3",
                "_rebuild_parameter"):
    setattr(utils, fname, _fake_function("torch._utils", fname))
  tensor_mod._rebuild_from_type_v2 = _fake_function("torch._tensor", "_rebuild_from_type_v2")
  tensor_mod.Tensor = type("Tensor", (), {"__module__": "torch._tensor"})
  param_mod.Parameter = type("Parameter", (), {"__module__": "torch.nn.parameter"})
  for cls in list(_STORAGE_NAMES.values()) + ["UntypedStorage"]:
    setattr(torch, cls, type(cls, (), {"__module__": "torch"}))
  for dtype in ("uint16", "float32", "bfloat16"):
    setattr(torch, dtype, _FakeDType(dtype))
  torch._utils, torch._tensor = utils, tensor_mod
  for name, mod in (("torch", torch), ("torch._utils", utils), ("torch._tensor", tensor_mod),
                    ("torch.nn", nn), ("torch.nn.parameter", param_mod)):
    monkeypatch.setitem(sys.modules, name, mod)
  return torch


class _Storage:

  def __init__(self, key, cls, numel, raw):
    self.key, self.cls, self.numel, self.raw = key, cls, numel, raw


class _Tensor:

  def __init__(self, fn, args):
    self.fn, self.args = fn, args

  def __reduce__(self):
    return self.fn, self.args


def _raw(arr, dtype):
  """Little-endian storage bytes of `arr` as torch `dtype`."""
  if dtype == "bfloat16":
    return (np.asarray(arr, "<f4").view("<u4") >> 16).astype("<u2").tobytes()
  return np.asarray(arr).astype(np.dtype(dtype).newbyteorder("<")).tobytes()


class _Builder:
  """Collects storages and tensors, then writes a zip or legacy torch file."""

  def __init__(self, torch):
    self.torch, self.storages = torch, {}

  def storage(self, flat, dtype):
    key = str(len(self.storages))
    cls = getattr(self.torch, _STORAGE_NAMES[dtype])
    self.storages[key] = _Storage(key, cls, np.size(flat), _raw(flat, dtype))
    return self.storages[key]

  def untyped(self, raw):
    key = str(len(self.storages))
    self.storages[key] = _Storage(key, self.torch.UntypedStorage, len(raw), raw)
    return self.storages[key]

  def tensor(self, storage, offset, size, stride, how="v2"):
    utils = self.torch._utils
    if how == "v1":
      return _Tensor(utils._rebuild_tensor, (storage, offset, size, stride))
    args = (storage, offset, tuple(size), tuple(stride), False, collections.OrderedDict())
    tensor = _Tensor(utils._rebuild_tensor_v2, args)
    if how == "param":
      return _Tensor(utils._rebuild_parameter, (tensor, True, collections.OrderedDict()))
    if how == "from_type":
      return _Tensor(self.torch._tensor._rebuild_from_type_v2,
                     (utils._rebuild_tensor_v2, self.torch._tensor.Tensor, args, {}))
    return tensor

  def array(self, arr, dtype, how="v2"):
    arr = np.asarray(arr)
    stride = [s // arr.itemsize for s in np.ascontiguousarray(arr).strides]
    return self.tensor(self.storage(arr.ravel(), dtype), 0, arr.shape, stride, how)

  def pickle(self, obj, legacy, protocol=2):
    buf = io.BytesIO()
    pickler = pickle.Pickler(buf, protocol=protocol)

    def persistent_id(o):
      if not isinstance(o, _Storage):
        return None
      pid = ("storage", o.cls, o.key, "cpu", o.numel)
      return pid + (None,) if legacy else pid

    pickler.persistent_id = persistent_id
    pickler.dump(obj)
    return buf.getvalue()

  def write_zip(self, path, obj, byteorder="little", prefix="archive"):
    with zipfile.ZipFile(path, "w") as zf:
      zf.writestr(f"{prefix}/data.pkl", self.pickle(obj, legacy=False))
      zf.writestr(f"{prefix}/byteorder", byteorder)
      for key, st in self.storages.items():
        raw = st.raw
        if byteorder == "big":
          item = len(raw) // max(st.numel, 1)
          raw = np.frombuffer(raw, f"<u{item}" if item > 1 else "u1").byteswap().tobytes()
        zf.writestr(f"{prefix}/data/{key}", raw)
      zf.writestr(f"{prefix}/version", "3\n")
    return path

  def write_legacy(self, path, obj, header=None, protocol=2):
    with open(path, "wb") as f:
      f.write(header if header is not None else _legacy_header(protocol=protocol))
      f.write(self.pickle(obj, legacy=True, protocol=protocol))
      pickle.dump(list(self.storages), f, protocol=protocol)
      for st in self.storages.values():
        f.write(struct.pack("<q", st.numel))
        f.write(st.raw)
    return path


def _legacy_header(magic=pickle_reader.LEGACY_MAGIC, protocol=2):
  sys_info = {"protocol_version": 1001, "little_endian": True,
              "type_sizes": {"short": 2, "int": 4, "long": 8}}
  return b"".join(pickle.dumps(x, protocol=protocol) for x in (magic, 1001, sys_info))


_DTYPE_VALUES = {
    "float64": np.array([[1.5, -2.25e300], [np.pi, 0]]),
    "float32": np.array([[1.5, -2.5, 3.0], [1e-30, 7, 8]], np.float32),
    "float16": np.array([0.5, -65504, 1e-4], np.float16),
    "bfloat16": np.array([[1.0, -2.0], [3.5, 0.0078125]], np.float32),
    "int64": np.array([2**40, -3, 0], np.int64),
    "int32": np.array([[2**30, -7]], np.int32),
    "int16": np.array([-32768, 32767], np.int16),
    "int8": np.array([-128, 5, 127], np.int8),
    "uint8": np.array([0, 255, 17], np.uint8),
    "bool": np.array([[True, False, True]]),
}


@pytest.mark.parametrize("fmt", ["zip", "legacy", "big"])
def test_every_dtype_round_trips(tmp_path, fake_torch, fmt):
  b = _Builder(fake_torch)
  sd = collections.OrderedDict((f"w.{k}", b.array(v, k)) for k, v in _DTYPE_VALUES.items())
  path = tmp_path / "dtypes.pth"
  if fmt == "legacy":
    b.write_legacy(path, sd)
  else:
    b.write_zip(path, sd, byteorder="big" if fmt == "big" else "little")
  out = torch_io.load_state_dict(path)
  assert list(out) == list(sd)
  for k, v in _DTYPE_VALUES.items():
    want_dtype = np.float32 if k == "bfloat16" else v.dtype
    assert out[f"w.{k}"].dtype == want_dtype, k
    assert out[f"w.{k}"].dtype.isnative
    np.testing.assert_array_equal(out[f"w.{k}"], v, err_msg=k)


@pytest.mark.parametrize("byteorder", ["LITTLE", ""])
def test_unknown_byteorder_record_is_refused(tmp_path, fake_torch, byteorder):
  # Any record but "little" read the weights as big-endian: values silently byte-swapped.
  # An empty record is no byte order either (the record is "little" or "big").
  b = _Builder(fake_torch)
  path = b.write_zip(tmp_path / "order.pth", {"w": b.array(np.ones(2, np.float32), "float32")},
                     byteorder=byteorder)
  with pytest.raises(CheckpointError, match=rf"order\.pth: unknown byteorder record "
                                            rf"{re.escape(repr(byteorder))}$"):
    torch_io.load_state_dict(path)


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_views_offsets_and_rebuild_variants(tmp_path, fake_torch, fmt):
  b = _Builder(fake_torch)
  base = np.arange(24, dtype=np.float32)
  st = b.storage(base, "float32")
  obj = {"state_dict": {
      "module.full": b.tensor(st, 0, (4, 6), (6, 1)),
      "module.transposed": b.tensor(st, 0, (6, 4), (1, 6)),
      "module.offset": b.tensor(st, 5, (2, 3), (3, 1)),
      "module.strided": b.tensor(st, 1, (3, 2), (8, 3)),
      "module.expanded": b.tensor(st, 2, (3, 2), (0, 1)),
      "module.scalar": b.tensor(st, 23, (), ()),
      "module.empty": b.tensor(st, 0, (0, 5), (5, 1)),
      "module.v1": b.tensor(st, 4, (2,), (1,), how="v1"),
      "module.param": b.tensor(st, 0, (2, 2), (2, 1), how="param"),
      "module.from_type": b.tensor(st, 6, (3,), (2,), how="from_type"),
  }, "epoch": 3}
  path = tmp_path / "views.pt"
  b.write_legacy(path, obj) if fmt == "legacy" else b.write_zip(path, obj)
  sd = torch_io.load_state_dict(path)
  grid = base.reshape(4, 6)
  np.testing.assert_array_equal(sd["full"], grid)
  np.testing.assert_array_equal(sd["transposed"], grid.T)
  np.testing.assert_array_equal(sd["offset"], base[5:11].reshape(2, 3))
  np.testing.assert_array_equal(sd["strided"], [[1, 4], [9, 12], [17, 20]])
  np.testing.assert_array_equal(sd["expanded"], [[2, 3]] * 3)
  assert sd["scalar"].shape == () and sd["scalar"] == 23
  assert sd["empty"].shape == (0, 5)
  np.testing.assert_array_equal(sd["v1"], [4, 5])
  np.testing.assert_array_equal(sd["param"], [[0, 1], [2, 3]])
  np.testing.assert_array_equal(sd["from_type"], [6, 8, 10])
  assert all(v.flags.c_contiguous and v.flags.writeable for v in sd.values())


@pytest.mark.parametrize("byteorder", ["little", "big"])
def test_v3_tensor_on_untyped_storage(tmp_path, fake_torch, byteorder):
  # An untyped storage is bytes: a big-endian file's elements are swapped when its v3 tensor
  # gives them their dtype (read as little-endian, 300 came back as 11265).
  b = _Builder(fake_torch)
  end = "<" if byteorder == "little" else ">"
  u16 = np.array([1, 65535, 300, 7], f"{end}u2")
  f32 = np.array([1.25, -3.0, 1e-30], f"{end}f4")
  st16, st32 = b.untyped(u16.tobytes()), b.untyped(f32.tobytes())
  utils = fake_torch._utils
  args16 = (st16, 1, (3,), (1,), False, collections.OrderedDict(), fake_torch.uint16)
  args32 = (st32, 0, (3,), (1,), False, collections.OrderedDict(), fake_torch.float32)
  obj = {"a": _Tensor(utils._rebuild_tensor_v3, args16),
         "b": _Tensor(utils._rebuild_tensor_v3, args32)}
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "v3.pth", obj, byteorder=byteorder))
  assert sd["a"].dtype == np.uint16 and sd["a"].dtype.isnative
  np.testing.assert_array_equal(sd["a"], [65535, 300, 7])
  assert sd["b"].dtype == np.float32 and sd["b"].dtype.isnative
  np.testing.assert_array_equal(sd["b"], np.array([1.25, -3.0, 1e-30], np.float32))


def test_float8_tensors_are_widened_to_float32(tmp_path, fake_torch):
  # float8_e4m3fn (bias 7): 0x3C = 1.5, 0xC0 = -2, 0x7E = 448, 0x01 = 2**-9 (subnormal).
  fake_torch.float8_e4m3fn = _FakeDType("float8_e4m3fn")
  b = _Builder(fake_torch)
  st = b.untyped(bytes([0x3C, 0xC0, 0x7E, 0x01]))
  args = (st, 0, (2, 2), (2, 1), False, collections.OrderedDict(), fake_torch.float8_e4m3fn)
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "f8.pth",
                                            {"w": _Tensor(fake_torch._utils._rebuild_tensor_v3,
                                                          args)}))
  assert sd["w"].dtype == np.float32
  np.testing.assert_array_equal(sd["w"], [[1.5, -2.0], [448.0, 2.0 ** -9]])


def test_legacy_storage_view_metadata(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  st = b.storage(np.arange(10, dtype=np.float32), "float32")
  path = tmp_path / "view.pth"

  def write(body, view):  # a legacy file whose storages are `view`s of `st`
    pid = ("storage", st.cls, st.key, "cpu", st.numel, view)
    with open(path, "wb") as f:
      f.write(_legacy_header() + _with_storage_id(body, pid)
              + pickle.dumps([st.key], protocol=2))
      f.write(struct.pack("<q", st.numel) + st.raw)

  body = {"x": b.tensor(st, 1, (2,), (1,))}
  write(body, ("view0", 4, 5))
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [5, 6])
  # A negative view offset sliced the base storage from its end: values of the wrong
  # elements, silently.
  for view in (("view0", -4, 5), ("view0", 4, -1)):
    write(body, view)
    with pytest.raises(CheckpointError, match=r"view\.pth: malformed storage view"):
      torch_io.load_state_dict(path)
  # A view reaching past its base storage's end (elements 8..12 of 10) is refused, even
  # where the tensor reads only the part that exists.
  write({"x": b.tensor(st, 0, (2,), (1,))}, ("view0", 8, 5))
  with pytest.raises(CheckpointError, match=r"view\.pth: storage view view0 lies outside its "
                                            r"base storage"):
    torch_io.load_state_dict(path)
  # At the boundary: a view ending at its base's last element (5..9 of 10) is read; one
  # element further (6..10) is refused. A view from element 0 is one.
  write({"x": b.tensor(st, 3, (2,), (1,))}, ("view0", 5, 5))
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [8, 9])
  write({"x": b.tensor(st, 1, (2,), (1,))}, ("view0", 0, 3))
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [1, 2])
  write({"x": b.tensor(st, 0, (2,), (1,))}, ("view0", 6, 5))
  with pytest.raises(CheckpointError, match=r"view0 lies outside its base storage"):
    torch_io.load_state_dict(path)
  # A view holds its own elements only: a tensor reading past them (4 of a 3-element view
  # at 4) is refused, though its base has them.
  write({"x": b.tensor(st, 0, (4,), (1,))}, ("view0", 4, 3))
  with pytest.raises(CheckpointError, match=r"view\.pth: tensor of size \(4,\), stride \(1,\), "
                                            r"offset 0 overruns its storage of 3 elements"):
    torch_io.load_state_dict(path)


def test_tensor_overrunning_storage_is_refused(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  st = b.storage(np.arange(6, dtype=np.float32), "float32")
  for size, stride, offset in [((7,), (1,), 0), ((2, 3), (3, 1), 1), ((3,), (3,), 0)]:
    b.write_zip(tmp_path / "bad.pth", {"x": b.tensor(st, offset, size, stride)})
    with pytest.raises(CheckpointError, match="overruns its storage"):
      torch_io.load_state_dict(tmp_path / "bad.pth")
  b.write_zip(tmp_path / "huge.pth", {"x": b.tensor(st, 0, (1 << 20, 1 << 20), (0, 0))})
  with pytest.raises(CheckpointError, match="refused a tensor"):
    torch_io.load_state_dict(tmp_path / "huge.pth")
  # numpy takes negative offsets and strides: they read memory before or after the storage's
  # buffer (the overrun check looks only at the last element's index).
  for offset, size, stride, match in ((0, (2,), (-1,), "tensor stride must be a tuple of "
                                       "non-negative ints"),
                                      (2, (3,), (-1,), "tensor stride must be"),
                                      (-1, (3,), (1,), "bad tensor storage offset -1"),
                                      (0, (2, -1), (1, 1), "tensor size must be a tuple of "
                                       "non-negative ints")):
    b.write_zip(tmp_path / "neg.pth", {"x": b.tensor(st, offset, size, stride)})
    with pytest.raises(CheckpointError, match=rf"neg\.pth: {match}"):
      torch_io.load_state_dict(tmp_path / "neg.pth")


def test_many_views_of_one_storage_are_refused_beyond_a_memory_budget(tmp_path, fake_torch,
                                                                       monkeypatch):
  # Each tensor is a copy: a small file of many full views (or expansions) of one storage
  # would take any amount of memory. Allowed: 4x the storages' bytes + the extra budget.
  monkeypatch.setattr(pickle_reader, "_EXTRA_TENSOR_BYTES", 1000)
  b = _Builder(fake_torch)
  st = b.storage(np.arange(100, dtype=np.float32), "float32")  # 400 bytes
  tied = {f"w{i}": b.tensor(st, 0, (100,), (1,)) for i in range(6)}  # 2400 <= 1000 + 1600
  b.write_zip(tmp_path / "tied.pth", tied)
  assert len(torch_io.load_state_dict(tmp_path / "tied.pth")) == 6
  b.write_zip(tmp_path / "many.pth", {f"w{i}": b.tensor(st, 0, (100,), (1,)) for i in range(7)})
  with pytest.raises(CheckpointError, match=r"many\.pth: refused: its tensors would take .* "
                     r"more than 4x the data the file holds"):
    torch_io.load_state_dict(tmp_path / "many.pth")
  # One tensor object under many names (tied weights) is one array, built and counted once.
  one = b.tensor(st, 0, (100,), (1,))
  b.write_zip(tmp_path / "one.pth", {f"w{i}": one for i in range(7)})
  sd = torch_io.load_state_dict(tmp_path / "one.pth")
  assert len(sd) == 7 and all(sd[f"w{i}"] is sd["w0"] for i in range(7))


def test_zip_with_missing_storage_record(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  obj = {"x": b.array(np.ones(3, np.float32), "float32")}
  path = tmp_path / "m.pth"
  with zipfile.ZipFile(path, "w") as zf:
    zf.writestr("archive/data.pkl", b.pickle(obj, legacy=False))
  with pytest.raises(CheckpointError, match="missing"):
    torch_io.load_state_dict(path)


def test_compressed_records_are_read_no_further_than_needed(tmp_path, fake_torch, monkeypatch):
  """A storage record that inflates far beyond its compressed size (a zip bomb: 64 MiB of
  zeros in ~64 KB) is refused before it is read, whether its tensor asks for all of it or
  not (a tensor of 2**24 zeros read 64 MiB from a 65 KB file); within that bound a record is
  read only as far as the tensor needs; an object pickle beyond `MAX_PICKLE_BYTES` is
  refused. An .npz's records are held to the same bound."""
  import tracemalloc  # pylint: disable=import-outside-toplevel
  b = _Builder(fake_torch)
  obj = {"x": b.array(np.arange(3, dtype=np.float32), "float32")}
  path = tmp_path / "bomb.pth"
  with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
    zf.writestr("archive/data.pkl", b.pickle(obj, legacy=False))
    key = next(iter(b.storages))
    zf.writestr(f"archive/data/{key}", b.storages[key].raw + bytes(64 << 20))
  assert path.stat().st_size < 1 << 20
  refused = r"bomb\.pth: zip record 'archive/data/\w+' inflates \d+ bytes to 67108876 \(\d+x, " \
            r"more than 100x\): not a checkpoint's weights"
  with pytest.raises(CheckpointError, match=refused):
    torch_io.load_state_dict(path)
  b2 = _Builder(fake_torch)  # the tensor declares every byte of the record
  whole = {"x": b2.array(np.zeros(1 << 24, np.float32), "float32")}
  with zipfile.ZipFile(tmp_path / "whole.pth", "w", compression=zipfile.ZIP_DEFLATED) as zf:
    zf.writestr("archive/data.pkl", b2.pickle(whole, legacy=False))
    key2 = next(iter(b2.storages))
    zf.writestr(f"archive/data/{key2}", b2.storages[key2].raw)
  with pytest.raises(CheckpointError, match=r"whole\.pth: zip record .* more than 100x"):
    torch_io.load_state_dict(tmp_path / "whole.pth")
  np.savez_compressed(tmp_path / "bomb.npz", w=np.zeros(1 << 24, np.float32))
  with pytest.raises(CheckpointError, match=r"bomb\.npz: zip record 'w\.npy' inflates"):
    torch_io.load_state_dict(tmp_path / "bomb.npz")
  monkeypatch.setattr(pickle_reader, "MAX_INFLATION", 1 << 40)  # within the bound
  tracemalloc.start()
  try:
    sd = torch_io.load_state_dict(path)
    peak = tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()
  np.testing.assert_array_equal(sd["x"], [0, 1, 2])
  assert peak < 8 << 20, peak  # the whole record: 64 MiB
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_BYTES", 16)
  with pytest.raises(CheckpointError, match=r"bomb\.pth.*zip record 'archive/data\.pkl' is "
                     r"larger than 16 bytes: not a model checkpoint's"):
    torch_io.load_state_dict(path)


def test_archives_that_would_take_memory_beyond_their_size_are_refused(tmp_path, fake_torch,
                                                                       monkeypatch):
  """Found by fuzzing: a record whose header declares 50x its compressed size passed the
  inflation bound; records of 1 MiB of zeros each passed one by one (a 1 MB file took 5 GB);
  two records of one name were read as the last one."""
  b = _Builder(fake_torch)
  obj = {"x": b.array(np.arange(3, dtype=np.float32), "float32")}
  path = tmp_path / "lie.pth"
  key = next(iter(b.storages))
  name = f"archive/data/{key}"
  with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
    zf.writestr("archive/data.pkl", b.pickle(obj, legacy=False))
    zf.writestr(name, b.storages[key].raw + bytes(64 << 20))  # ~1000x
  with zipfile.ZipFile(path) as zf:
    info = zf.getinfo(name)
  raw = bytearray(path.read_bytes())  # the central directory declares 50x the real size
  at = raw.index(b"PK\x01\x02", raw.index(b"PK\x01\x02") + 1)  # the second entry's
  assert raw[at + 46:at + 46 + len(name)] == name.encode()
  assert int.from_bytes(raw[at + 20:at + 24], "little") == info.compress_size
  raw[at + 20:at + 24] = (50 * info.compress_size).to_bytes(4, "little")
  path.write_bytes(bytes(raw))
  with pytest.raises(CheckpointError, match=r"lie\.pth: .*inflates? \d{5} bytes to "
                                            r"671\d{5} "):  # its real size, not 50x that
    torch_io.load_state_dict(path)
  many = {f"w{i}": np.zeros((1 << 18) - 64, np.float32) for i in range(20)}  # 20 x ~1 MiB
  np.savez_compressed(tmp_path / "many.npz", **many)
  assert (tmp_path / "many.npz").stat().st_size < 1 << 20
  with pytest.raises(CheckpointError, match=r"many\.npz: its compressed zip records inflate "
                                            r"\d+ bytes to \d+ together \(more than 100x"):
    torch_io.load_state_dict(tmp_path / "many.npz")
  np.savez_compressed(tmp_path / "few.npz", **dict(list(many.items())[:4]))  # 4 MiB: free
  assert len(torch_io.load_state_dict(tmp_path / "few.npz")) == 4
  # The bound is the archive's, whatever the records' order: zeros first, then weights that
  # barely compress, is a checkpoint (a running total refused it at the 18th zero record).
  weights = np.random.default_rng(0).standard_normal(1 << 16).astype(np.float32)
  np.savez_compressed(tmp_path / "zeros_first.npz", **many, z=weights)
  assert len(torch_io.load_state_dict(tmp_path / "zeros_first.npz")) == 21
  with pytest.warns(UserWarning, match="Duplicate name"):
    with zipfile.ZipFile(tmp_path / "twice.pth", "w") as zf:
      zf.writestr("archive/data.pkl", b.pickle(obj, legacy=False))
      zf.writestr(name, b.storages[key].raw)
      zf.writestr(name, np.float32([7, 8, 9]).tobytes())
  with pytest.raises(CheckpointError, match=rf"twice\.pth: zip file with records of the same "
                                            rf"name \(\['{name}'\]\)"):
    torch_io.load_state_dict(tmp_path / "twice.pth")
  # A corrupt deflate stream in an .npz: one line (zlib.error escaped as a traceback).
  np.savez_compressed(tmp_path / "bad.npz", w=np.arange(1000, dtype=np.float32))
  with zipfile.ZipFile(tmp_path / "bad.npz") as zf:
    info = zf.infolist()[0]
  raw = bytearray((tmp_path / "bad.npz").read_bytes())
  off = info.header_offset  # the deflate stream begins after the local header's name, extra
  off += 30 + int.from_bytes(raw[off + 26:off + 28], "little") + int.from_bytes(
      raw[off + 28:off + 30], "little")
  raw[off] = 0xFF  # BFINAL 1, BTYPE 3: an invalid block type
  (tmp_path / "bad.npz").write_bytes(bytes(raw))
  with pytest.raises(CheckpointError, match=r"bad\.npz: cannot read \.npz file .*error"):
    torch_io.load_state_dict(tmp_path / "bad.npz")


def _pickle_with_ops(ops: bytes) -> bytes:
  return b"\x80\x02" + ops + b"."  # protocol 2 ... STOP


def test_pickles_that_would_take_memory_beyond_their_size_are_refused(tmp_path, monkeypatch):
  """One LONG_BINPUT of a huge index made the C unpickler allocate a memo of that size (a
  548-byte file took 4.3 GB); the opcodes bound the objects built; refused globals read as
  placeholders each made a class."""
  memo = _pickle_with_ops(b"}" + b"r" + (1 << 22).to_bytes(4, "little"))  # EMPTY_DICT, PUT
  for legacy in (False, True):
    path = tmp_path / f"memo_{legacy}.pth"
    if legacy:
      path.write_bytes(memo)
    else:
      with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("archive/data.pkl", memo)
    with pytest.raises(CheckpointError, match=r"stores into memo slot 4194304 after 3 opcodes: "
                                              r"not a checkpoint's pickle"):
      torch_io.load_state_dict(path, opaque_unknown=True)
  # A training checkpoint with a per-step log of 300k steps (~2.4 million opcodes) loads.
  log_ops = sum(1 for _ in pickletools.genops(pickle.dumps(
      [{"step": i, "loss": float(i)} for i in range(300000)], protocol=2)))
  assert 2_000_000 < log_ops < pickle_reader.MAX_PICKLE_OPS
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_OPS", 50)
  lists = _pickle_with_ops(b"]" * 60 + b"0" * 59)  # 60 empty lists, 59 POPs
  with zipfile.ZipFile(tmp_path / "ops.pth", "w") as zf:
    zf.writestr("archive/data.pkl", lists)
  with pytest.raises(CheckpointError, match="a pickle of more than 50 opcodes"):
    torch_io.load_state_dict(tmp_path / "ops.pth")
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_OPS", 1 << 21)
  monkeypatch.setattr(pickle_reader, "MAX_REFUSED_GLOBALS", 2)
  ops = b"".join(b"c" + f"mod{i % 3}\nObj\n".encode() + b"0" for i in range(6)) + b"}"
  with zipfile.ZipFile(tmp_path / "globals.pth", "w") as zf:
    zf.writestr("archive/data.pkl", _pickle_with_ops(ops))
  with pytest.raises(CheckpointError, match="more than 2 different pickled globals"):
    torch_io.load_state_dict(tmp_path / "globals.pth", opaque_unknown=True)
  unpickler = pickle_reader.RestrictedUnpickler(io.BytesIO(b""), "x", opaque_unknown=True)
  assert unpickler.find_class("m", "A") is unpickler.find_class("m", "A")  # one class a name


# --------------------------------------------------------------------------------------------
# Malicious pickles: nothing may run.


class _Evil:
  """Pickles as a call of `fn(*args)`."""

  def __init__(self, fn, *args):
    self.fn, self.args = fn, args

  def __reduce__(self):
    return self.fn, self.args


def _evil_payloads(marker):
  cmd = f"touch {marker}"
  code = f"open({str(marker)!r}, 'w').close()"
  payloads = {}
  for proto in (0, 2, 4):  # GLOBAL (0, 2) and STACK_GLOBAL (4)
    payloads[f"os.system/p{proto}"] = pickle.dumps({"w": _Evil(os.system, cmd)}, protocol=proto)
    payloads[f"eval/p{proto}"] = pickle.dumps({"w": _Evil(eval, code)}, protocol=proto)
  # INST opcode (protocol 0) and a hand-written GLOBAL + REDUCE.
  payloads["inst"] = f"(S'{cmd}'\nios\nsystem\n.".encode()
  payloads["raw_reduce"] = f"cbuiltins\neval\n(S\"{code}\"\ntR.".encode()
  return payloads


def _assert_refused(path, marker, fn):
  """Refused as the payload's own global `fn` ('system' or 'eval', any module spelling)."""
  with pytest.raises(CheckpointError) as err:
    torch_io.load_checkpoint_object(path)
  assert str(path) in str(err.value)
  assert re.search(rf"refusing to load the pickled global '(os|posix|builtins|__builtin__)\.{fn}'",
                   str(err.value)), (fn, str(err.value))
  assert not marker.exists(), "pickled code was executed"


@pytest.mark.parametrize("where", ["zip", "legacy_body", "legacy_magic", "legacy_keys"])
def test_malicious_pickles_are_refused(tmp_path, where):
  marker = tmp_path / "pwned"
  for name, payload in _evil_payloads(marker).items():
    path = tmp_path / f"evil_{name.replace('/', '_')}.pth"
    if where == "zip":
      with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("evil/data.pkl", payload)
    elif where == "legacy_body":
      path.write_bytes(_legacy_header() + payload + pickle.dumps([], protocol=2))
    elif where == "legacy_magic":
      if not payload.startswith(b"\x80"):
        continue  # not recognised as a pickle at all
      path.write_bytes(payload)
    else:
      body = pickle.dumps({"a": 1}, protocol=2)
      path.write_bytes(_legacy_header() + body + payload)
    _assert_refused(path, marker, "system" if name.startswith(("os.system", "inst")) else "eval")
    if where == "legacy_magic":  # a plain pickle: no weights to read beside its objects
      with pytest.raises(CheckpointError, match="not a torch checkpoint: refusing") as e:
        torch_io.load_checkpoint_object(path)
      assert "opaque_unknown" not in str(e.value)


def test_malicious_pickle_with_opaque_unknown_runs_nothing(tmp_path):
  marker = tmp_path / "pwned"
  path = tmp_path / "evil.pth"
  with zipfile.ZipFile(path, "w") as zf:
    payload = {"model": {"w": _Evil(os.system, f"touch {marker}")}, "sched": _Evil(eval, "1")}
    zf.writestr("archive/data.pkl", pickle.dumps(payload, protocol=2))
  obj = torch_io.load_checkpoint_object(path, opaque_unknown=True)
  assert isinstance(obj["model"]["w"], pickle_reader.OpaqueObject)
  assert "system" in obj["model"]["w"].name
  assert not marker.exists()
  with pytest.raises(CheckpointError, match="not a state dict of tensors"):
    torch_io.load_state_dict(path, opaque_unknown=True)
  assert not marker.exists()


def test_npz_with_pickled_objects_runs_nothing(tmp_path):
  # np.savez pickles object arrays; np.load(allow_pickle=True) would run them on reading.
  marker = tmp_path / "pwned"
  evil = np.empty(1, dtype=object)
  evil[0] = _Evil(os.system, f"touch {marker}")
  np.savez(tmp_path / "evil.npz", w=np.ones(2, np.float32), x=evil)
  with pytest.raises(CheckpointError, match=r"evil\.npz: cannot read \.npz file \(array 'x'\)"):
    torch_io.load_state_dict(tmp_path / "evil.npz")
  assert not marker.exists(), "pickled code was executed"


def test_the_allow_list_holds_only_inert_stand_ins():
  # What find_class may hand the unpickler: this module's helpers and markers, and
  # OrderedDict (a C container); never a callable of builtins, os, torch, ...
  inert = (pickle_reader._SafeFunction, pickle_reader._TypeMarker, pickle_reader.TorchDType)
  for key, obj in pickle_reader.SAFE_GLOBALS.items():
    assert isinstance(obj, inert) or obj is collections.OrderedDict, key
    if isinstance(obj, pickle_reader._SafeFunction):
      assert obj.fn.__module__ == pickle_reader.__name__, key
  unpickler = pickle_reader.RestrictedUnpickler(io.BytesIO(b""), "x")
  for module, name in (("builtins", "getattr"), ("builtins", "__import__"), ("torch", "load"),
                       ("numpy", "frombuffer"), ("collections", "Counter")):
    with pytest.raises(pickle_reader.RefusedGlobal, match=rf"'{module}\.{name}'"):
      unpickler.find_class(module, name)


class _Scheduler:
  """Stands for an LR scheduler pickled by value (old OneCycleLR state held a bound method)."""

  def __init__(self):
    self.last_epoch, self.anneal_func = 3, self.anneal

  def anneal(self):
    return self.last_epoch


def test_opaque_unknown_extracts_weights_next_to_junk(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  junk = {"counter": _Evil(collections.Counter, [1, 2]), "sched": _Scheduler(),
          "method": _Scheduler().anneal}
  ckpt = {"model": {"fnet.w": b.array(np.ones(2, np.float32), "float32")}, "scheduler": junk}
  path = b.write_zip(tmp_path / "train.pth", ckpt)
  with pytest.raises(CheckpointError, match="collections.Counter"):
    torch_io.load_state_dict(path)
  sd = torch_io.load_state_dict(path, opaque_unknown=True)
  np.testing.assert_array_equal(sd["fnet.w"], [1, 1])
  sched = torch_io.load_checkpoint_object(path, opaque_unknown=True)["scheduler"]
  assert all(isinstance(v, pickle_reader.OpaqueObject) for v in sched.values())
  assert sched["sched"].name.endswith("_Scheduler")


def test_tools_read_the_weights_of_training_checkpoints_with_pickled_objects(tmp_path,
                                                                            fake_torch, caplog):
  # An official training checkpoint saved with torch 2.1 holds OneCycleLR's anneal function
  # in "scheduler": `sav-jax convert`, `infer --vda`, training's init_from read its weights.
  b = _Builder(fake_torch)
  ckpt = {"model": {"fnet.w": b.array(np.ones(2, np.float32), "float32")},
          "scheduler": {"anneal_func": _Scheduler().anneal}, "total_steps": 3000}
  path = b.write_zip(tmp_path / "model_sav_003000.pth", ckpt)
  with caplog.at_level(logging.WARNING):
    sd = torch_io.load_state_dict_of_kind(path, "sav")
  np.testing.assert_array_equal(sd["fnet.w"], [1, 1])
  assert "inert placeholders" in caplog.text and "_Scheduler" in caplog.text
  with pytest.raises(CheckpointError, match=r"opaque_unknown=True\) reads the weights"):
    torch_io.load_state_dict(path)


def test_build_cannot_mutate_allow_listed_objects(tmp_path, torch_dir):
  # GLOBAL torch.FloatStorage, then BUILD with slot state {'raw': 1}.
  payload = b"\x80\x02ctorch\nFloatStorage\nN}X\x03\x00\x00\x00rawK\x01s\x86b."
  # BUILD with a plain state dict on a rebuild function.
  payload2 = b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n}X\x02\x00\x00\x00fnK\x01sb."
  # BUILD with slot state {'fn': 1} on the rebuild function.
  payload3 = b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\nN}X\x02\x00\x00\x00fnK\x01s\x86b."
  # BUILD with a plain state dict on a dtype marker.
  payload4 = b"\x80\x02ctorch\nfloat32\n}X\x03\x00\x00\x00rawK\x01sb."
  # BUILD with both a plain state dict and slot state {'fn': 1} on the rebuild function.
  payload5 = (b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n}X\x01\x00\x00\x00aK\x01s"
              b"}X\x02\x00\x00\x00fnK\x01s\x86b.")
  # Each refusal is the one meant (not any error): the frozen object's own for slot state,
  # and for any other state an explicit refusal of BUILD on an object that takes no state
  # (not the accidental AttributeError of the missing __dict__, reported as corruption).
  no_state = (r"build{}\.pth: refused the pickle BUILD opcode on a {}: it takes no state "
              r"\(setting state on the reader's objects is not allowed in a checkpoint; the "
              r"file may be malicious\)$")
  for i, (data, why) in enumerate((
      (payload, r"refused to set attribute 'raw' of TorchDType$"),
      (payload2, no_state.format(1, "_SafeFunction")),
      (payload3, r"refused to set attribute 'fn' of _SafeFunction$"),
      (payload4, no_state.format(3, "TorchDType")),
      (payload5, no_state.format(4, "_SafeFunction")))):
    path = tmp_path / f"build{i}.pth"
    with zipfile.ZipFile(path, "w") as zf:
      zf.writestr("archive/data.pkl", data)
    with pytest.raises(CheckpointError, match=why):
      torch_io.load_checkpoint_object(path)
  assert pickle_reader.SAFE_GLOBALS[("torch", "FloatStorage")].raw == np.dtype("<f4")
  assert (pickle_reader.SAFE_GLOBALS[("torch._utils", "_rebuild_tensor_v2")].fn
          is pickle_reader._rebuild_tensor_v2)  # pylint: disable=protected-access
  torch_io.load_state_dict(torch_dir / "plain_state_dict.pth")


def test_unexpected_persistent_id_is_refused(tmp_path):
  class ModulePickler(pickle.Pickler):
    def persistent_id(self, o):
      return ("module", "Net", "source.py", "def f(): pass") if o == "m" else None

  buf = io.BytesIO()
  ModulePickler(buf, protocol=2).dump({"net": "m"})
  path = tmp_path / "module.pth"
  with zipfile.ZipFile(path, "w") as zf:
    zf.writestr("archive/data.pkl", buf.getvalue())
  with pytest.raises(CheckpointError, match="persistent id 'module'"):
    torch_io.load_checkpoint_object(path)


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_storage_ids_of_the_other_format_are_malformed(tmp_path, fake_torch, fmt):
  # A zip storage id has 5 fields, a legacy one 6 (the last: a view of the storage): one of
  # the other length is refused, not read with its view ignored or its fields shifted.
  b = _Builder(fake_torch)
  st = b.storage(np.arange(10, dtype=np.float32), "float32")
  body = {"x": b.tensor(st, 0, (2,), (1,))}
  pid = ("storage", st.cls, st.key, "cpu", st.numel)
  pid = pid + (("view0", 4, 5),) if fmt == "zip" else pid
  data = _with_storage_id(body, pid)
  path = tmp_path / "other.pth"
  if fmt == "zip":
    with zipfile.ZipFile(path, "w") as zf:
      zf.writestr("archive/data.pkl", data)
      zf.writestr("archive/data/0", st.raw)
  else:
    with open(path, "wb") as f:
      f.write(_legacy_header() + data + pickle.dumps([st.key], protocol=2))
      f.write(struct.pack("<q", st.numel) + st.raw)
  with pytest.raises(CheckpointError, match=r"other\.pth: malformed storage id"):
    torch_io.load_state_dict(path)


def _with_storage_id(body, pid) -> bytes:
  """`body` pickled (protocol 2) with `pid` as the persistent id of every storage in it."""

  class Pickler(pickle.Pickler):
    def persistent_id(self, o):
      return pid if isinstance(o, _Storage) else None

  buf = io.BytesIO()
  Pickler(buf, protocol=2).dump(body)
  return buf.getvalue()


def _zip_with_pickle(path, data, extra=()):
  with zipfile.ZipFile(path, "w") as zf:
    zf.writestr("archive/data.pkl", data)
    for name in extra:
      zf.writestr(name, b"")
  return path


def test_errors_from_rebuild_helpers_name_the_file(tmp_path):
  # _codecs.encode with an encoding outside the allow-list.
  data = b"\x80\x02c_codecs\nencode\nX\x01\x00\x00\x00aX\x05\x00\x00\x00rot13\x86R."
  path = _zip_with_pickle(tmp_path / "codec.pth", data)
  with pytest.raises(CheckpointError, match=r"codec\.pth: refused _codecs\.encode"):
    torch_io.load_checkpoint_object(path)
  # Without an encoding, _codecs.encode encodes as UTF-8 (Python's default): 'é' is C3 A9.
  data = b"\x80\x02c_codecs\nencode\nX\x02\x00\x00\x00\xc3\xa9\x85R."
  assert torch_io.load_checkpoint_object(_zip_with_pickle(tmp_path / "u.pth", data)) == b"\xc3\xa9"
  # protocol-2 bytes objects (latin1), sets and complex numbers are fine.
  obj = {"b": b"\xff\x00", "s": {1, 2}, "f": frozenset([3]), "c": 1 + 2j, "t": (1, [2])}
  path = _zip_with_pickle(tmp_path / "plain.pth", pickle.dumps(obj, protocol=2))
  assert torch_io.load_checkpoint_object(path) == obj


def test_torch_size_in_a_checkpoint_is_a_tuple(tmp_path, fake_torch):
  # torch.Size pickles as `GLOBAL torch Size` called with its dims (e.g. shapes kept in a
  # training checkpoint's metadata): read as a tuple of ints, the weights beside it too.
  fake_torch.Size = _fake_function("torch", "Size")
  b = _Builder(fake_torch)
  obj = {"model": {"w": b.array(np.arange(6, dtype=np.float32).reshape(2, 3), "float32")},
         "shape": _Tensor(fake_torch.Size, ((2, 3),)), "empty": _Tensor(fake_torch.Size, ((),))}
  out = torch_io.load_checkpoint_object(b.write_zip(tmp_path / "size.pth", obj))
  assert out["shape"] == (2, 3) and isinstance(out["shape"], tuple) and out["empty"] == ()
  np.testing.assert_array_equal(out["model"]["w"], [[0, 1, 2], [3, 4, 5]])
  bad = {"shape": _Tensor(fake_torch.Size, ((2, -1),))}
  with pytest.raises(CheckpointError, match=r"torch\.Size must be a tuple of non-negative"):
    torch_io.load_checkpoint_object(b.write_zip(tmp_path / "bad_size.pth", bad))


def test_rebuild_helpers_refuse_what_is_not_a_tensor(tmp_path, fake_torch):
  # A parameter is rebuilt from a tensor, a v3 tensor names its dtype: anything else is a
  # malformed (or crafted) file, refused by name rather than returned as a "weight".
  b = _Builder(fake_torch)
  utils = fake_torch._utils
  st = b.storage(np.arange(4, dtype=np.float32), "float32")
  v3 = lambda dtype: _Tensor(utils._rebuild_tensor_v3,
                             (st, 0, (4,), (1,), False, collections.OrderedDict(), dtype))
  cases = {
      "param": ({"w": _Tensor(utils._rebuild_parameter, ([1.0, 2.0], True,
                                                         collections.OrderedDict()))},
                r"parameter rebuilt from a list, not a tensor"),
      "v3_none": ({"w": v3(None)}, r"_rebuild_tensor_v3 needs a torch dtype, got None"),
      "v3_str": ({"w": v3("float32")}, r"_rebuild_tensor_v3 needs a torch dtype"),
  }
  for name, (obj, message) in cases.items():
    path = b.write_zip(tmp_path / f"{name}.pth", obj)
    with pytest.raises(CheckpointError, match=rf"{name}\.pth: .*{message}"):
      torch_io.load_checkpoint_object(path)
  np.testing.assert_array_equal(  # the same v3 tensor with its dtype is read
      torch_io.load_state_dict(b.write_zip(tmp_path / "ok.pth", {"w": v3(fake_torch.float32)}))
      ["w"], [0, 1, 2, 3])


def test_records_without_a_prefix_folder_are_read(tmp_path, fake_torch):
  # `data.pkl` and `data/<key>` at the archive's root (an empty record prefix) are a
  # checkpoint as well.
  b = _Builder(fake_torch)
  sd = {"w": b.array(np.array([[1.5, -2.0]], np.float32), "float32")}
  path = tmp_path / "flat.pth"
  with zipfile.ZipFile(path, "w") as zf:
    zf.writestr("data.pkl", b.pickle(sd, legacy=False))
    zf.writestr("data/0", b.storages["0"].raw)
  out = torch_io.load_state_dict(path)
  assert list(out) == ["w"] and out["w"].dtype == np.float32
  np.testing.assert_array_equal(out["w"], [[1.5, -2.0]])


@pytest.mark.parametrize("names", [["code/__torch__/m.py", "constants.pkl"],
                                   ["outer/archive/data.pkl", "outer/archive/code/m.py"]])
def test_torchscript_code_without_a_checkpoints_data_pkl_is_named(tmp_path, names):
  # No single `<dir>/data.pkl` record, but a TorchScript `code/` folder: named as such.
  path = tmp_path / "scripted.pt"
  with zipfile.ZipFile(path, "w") as zf:
    for name in names:
      zf.writestr(name, b"")
  with pytest.raises(CheckpointError, match=r"scripted\.pt: a TorchScript archive"):
    torch_io.load_checkpoint_object(path)
  with zipfile.ZipFile(path, "w") as zf:  # neither a checkpoint nor TorchScript
    zf.writestr("weights/0", b"")
  with pytest.raises(CheckpointError, match=r"scripted\.pt: zip file without a single"):
    torch_io.load_checkpoint_object(path)


def test_self_references_stay_shared_and_a_tuple_holding_itself_is_refused(tmp_path):
  cyclic = []
  cyclic.append(cyclic)
  shared = [1]
  obj = {"cyclic": cyclic, "a": shared, "b": shared}
  out = torch_io.load_checkpoint_object(_zip_with_pickle(tmp_path / "lists.pth",
                                                         pickle.dumps(obj, protocol=2)))
  assert out["cyclic"][0] is out["cyclic"] and out["a"] is out["b"] == [1]
  loop = ([],)
  loop[0].append(loop)  # a tuple cannot be rebuilt before its items
  path = _zip_with_pickle(tmp_path / "loop.pth", pickle.dumps({"t": loop}, protocol=2))
  with pytest.raises(CheckpointError, match=r"loop\.pth: self-referencing tuple"):
    torch_io.load_checkpoint_object(path)


def test_deeply_nested_structure(tmp_path):
  depth = 5000
  data = b"\x80\x02" + b"]" * depth + b"a" * (depth - 1) + b"."
  with pytest.raises(CheckpointError, match="deep.pth"):
    torch_io.load_checkpoint_object(_zip_with_pickle(tmp_path / "deep.pth", data))


def test_torchscript_archive(tmp_path, fake_torch):
  path = _zip_with_pickle(tmp_path / "ts.pt", pickle.dumps({}), extra=["archive/code/m.py"])
  with pytest.raises(CheckpointError, match="TorchScript"):
    torch_io.load_checkpoint_object(path)
  path = _zip_with_pickle(tmp_path / "ts2.pt", pickle.dumps({}), extra=["archive/constants.pkl"])
  with pytest.raises(CheckpointError, match="TorchScript"):
    torch_io.load_checkpoint_object(path)
  # torch.save names the records after the file's stem: code.pth holds code/data.pkl,
  # which is a checkpoint, not TorchScript's code/ folder.
  b = _Builder(fake_torch)
  path = b.write_zip(tmp_path / "code.pth", {"w": b.array(np.ones(2, np.float32), "float32")},
                     prefix="code")
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["w"], [1, 1])


def test_legacy_file_of_pickle_protocol_1(tmp_path, fake_torch):
  # torch.save(..., pickle_protocol=1, _use_new_zipfile_serialization=False) starts with
  # the magic number as a protocol-1 long (b"L1195...L\n"), not with a protocol opcode.
  # (Protocol 0 cannot hold torch's tuple storage ids: torch cannot load those either.)
  protocol = 1
  b = _Builder(fake_torch)
  path = b.write_legacy(tmp_path / "old.pth", {"w": b.array(np.arange(3, dtype=np.float32),
                                                            "float32")}, protocol=protocol)
  assert path.read_bytes().startswith(b"L%d" % pickle_reader.LEGACY_MAGIC)
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["w"], [0, 1, 2])


# --------------------------------------------------------------------------------------------
# Broken files.


def test_missing_file_directory_and_unknown_suffix(tmp_path):
  with pytest.raises(CheckpointError, match="not found"):
    torch_io.load_state_dict(tmp_path / "nope.pth")
  with pytest.raises(CheckpointError, match="not a regular file"):
    torch_io.load_state_dict(tmp_path)
  (tmp_path / "w.txt").write_bytes(b"hello")
  with pytest.raises(CheckpointError, match="unknown checkpoint suffix '.txt'"):
    torch_io.load_state_dict(tmp_path / "w.txt")


@pytest.mark.parametrize("fname", ["sav_subset_zip.pth", "sav_subset_legacy.pth",
                                   "plain_state_dict.pth"])
def test_truncated_real_files(tmp_path, torch_dir, fname):
  data = (torch_dir / fname).read_bytes()
  legacy = fname.endswith("legacy.pth")
  if legacy:  # the raw storages follow five pickles (magic, protocol, sys info, object, keys)
    stream = io.BytesIO(data)
    for _ in range(5):
      collections.deque(pickletools.genops(stream), maxlen=0)
    storages_at = stream.tell()
  for cut in (0, 1, 7, 20, 150, len(data) // 3, len(data) // 2, len(data) - 100, len(data) - 1):
    path = tmp_path / f"cut{cut}.pth"
    path.write_bytes(data[:cut])
    with pytest.raises(CheckpointError) as err:
      torch_io.load_checkpoint_object(path)
    # A truncation, told as one for this file's format; a wrapped error is one a short read
    # gives (not, say, an AttributeError from a bug in the reader).
    kind = "legacy torch" if legacy else "torch zip"
    if cut == 0:
      want = "empty file$"
    elif legacy and cut >= storages_at:
      want = r"truncated legacy checkpoint \(storage '\d+' needs \d+ bytes, \d+ left\)$"
    elif not legacy and cut < 4:  # not even the zip magic
      want = r"not a torch checkpoint \(neither a zip archive nor a legacy pickle"
    else:
      want = rf"corrupt or truncated {kind} checkpoint \((BadZipFile|ValueError|EOFError): "
    assert re.match(re.escape(str(path)) + ": " + want, str(err.value)), (cut, str(err.value))


def test_corrupted_zip_record(tmp_path, torch_dir):
  data = bytearray((torch_dir / "plain_state_dict.pth").read_bytes())
  pos = data.index(b"ccollections")  # inside the stored (uncompressed) data.pkl
  data[pos:pos + 5] = b"XXXXX"
  path = tmp_path / "crc.pth"
  path.write_bytes(bytes(data))
  with pytest.raises(CheckpointError, match=r"crc\.pth"):
    torch_io.load_state_dict(path)


@pytest.mark.parametrize("prefix", [b"", b"\x80", b"\x80\x02", b"PK\x03\x04"])
@pytest.mark.parametrize("suffix", [".pth", ".bin", ".npz", ".safetensors"])
def test_random_bytes(tmp_path, prefix, suffix):
  rng = np.random.default_rng(len(prefix) + len(suffix))
  for i in range(5):
    path = tmp_path / f"rand{i}{suffix}"
    path.write_bytes(prefix + rng.integers(0, 256, 300 * (i + 1), np.uint8).tobytes())
    with pytest.raises(CheckpointError, match=f"rand{i}"):
      torch_io.load_state_dict(path)


def test_npz_files_that_are_not_archives_or_declare_huge_arrays_are_named(tmp_path):
  """Not a zip: NumPy called it pickled data (allow_pickle); a member whose header declares
  2**36 values escaped as a MemoryError that named nothing."""
  (tmp_path / "text.npz").write_bytes(b"version https://git-lfs.github.com/spec/v1\n")
  with pytest.raises(CheckpointError, match=r"text\.npz: not an \.npz archive \(an \.npz "
                     r"file is a zip archive; this one starts with b'versio'\)"):
    torch_io.load_state_dict(tmp_path / "text.npz")
  np.save(tmp_path / "one.npy", np.zeros(3))
  (tmp_path / "one.npz").write_bytes((tmp_path / "one.npy").read_bytes())
  with pytest.raises(CheckpointError, match=r"one\.npz: not an \.npz archive \(a single"):
    torch_io.load_state_dict(tmp_path / "one.npz")
  header = {"descr": "<f4", "fortran_order": False, "shape": (1 << 36,)}
  buf = io.BytesIO()
  np.lib.format.write_array_header_1_0(buf, header)
  with zipfile.ZipFile(tmp_path / "huge.npz", "w") as zf:
    zf.writestr("w.npy", buf.getvalue() + bytes(16))
  with pytest.raises(CheckpointError, match=r"huge\.npz: (declares an array too large to read: "
                     r"corrupt\?|cannot read \.npz file) \(array 'w'\)"):
    torch_io.load_state_dict(tmp_path / "huge.npz")


def test_empty_and_tar_files(tmp_path):
  (tmp_path / "e.pth").write_bytes(b"")
  with pytest.raises(CheckpointError, match="empty file"):
    torch_io.load_state_dict(tmp_path / "e.pth")
  tar = bytearray(600)
  tar[257:262] = b"ustar"
  (tmp_path / "old.tar").write_bytes(bytes(tar))
  with pytest.raises(CheckpointError, match="tar checkpoint format"):
    torch_io.load_state_dict(tmp_path / "old.tar")


def test_legacy_bad_magic_and_protocol(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  obj = {"x": b.array(np.ones(2, np.float32), "float32")}
  b.write_legacy(tmp_path / "magic.pth", obj, header=_legacy_header(magic=12345))
  with pytest.raises(CheckpointError, match="magic"):
    torch_io.load_state_dict(tmp_path / "magic.pth")
  header = b"".join(pickle.dumps(x, protocol=2) for x in (pickle_reader.LEGACY_MAGIC, 1002, {}))
  b.write_legacy(tmp_path / "proto.pth", obj, header=header)
  with pytest.raises(CheckpointError, match="protocol version 1002"):
    torch_io.load_state_dict(tmp_path / "proto.pth")


def test_legacy_huge_storage_count_is_truncation(tmp_path, fake_torch):
  b = _Builder(fake_torch)
  st = b.storage(np.ones(2, np.float32), "float32")
  path = tmp_path / "huge.pth"
  with open(path, "wb") as f:
    f.write(_legacy_header() + b.pickle({"x": b.tensor(st, 0, (2,), (1,))}, legacy=True))
    f.write(pickle.dumps([st.key], protocol=2) + struct.pack("<q", 1 << 60) + st.raw)
  with pytest.raises(CheckpointError, match="truncated"):
    torch_io.load_state_dict(path)
  for count in (1, -1):  # fewer elements than declared: said so ("needs 4 bytes, 8 left")
    with open(path, "wb") as f:
      f.write(_legacy_header() + b.pickle({"x": b.tensor(st, 0, (2,), (1,))}, legacy=True))
      f.write(pickle.dumps([st.key], protocol=2) + struct.pack("<q", count) + st.raw)
    with pytest.raises(CheckpointError, match=rf"corrupt legacy checkpoint \(storage '0' holds "
                                              rf"{count} elements, its persistent id declares 2\)"):
      torch_io.load_state_dict(path)


# --------------------------------------------------------------------------------------------
# Unwrapping and kind detection.


def _tiny(keys):
  return {k: np.zeros((1,), np.float32) for k in keys}


def _manifest_keys(fixtures_dir, name):
  return [e["name"] for e in json.loads((fixtures_dir / name).read_text())["keys"]]


def test_unwrap_forms():
  sd = _tiny(["a.w", "b.module.w"])
  assert torch_io.unwrap_state_dict(sd) == sd
  wrapped = {"model": {"module." + k: v for k, v in sd.items()}, "optimizer": {"state": {}},
             "scheduler": {"last_epoch": 3}, "total_steps": 10}
  assert list(torch_io.unwrap_state_dict(wrapped)) == ["a.w", "b.module.w"]
  assert list(torch_io.unwrap_state_dict({"state_dict": sd, "epoch": 1})) == list(sd)
  assert list(torch_io.unwrap_state_dict({"state_dict": {"model": sd}})) == list(sd)
  assert list(torch_io.unwrap_state_dict({"model": {"state_dict": {"model": sd}}})) == list(sd)
  # A wrapper key naming something else (the model's name) is not the weights' wrapper.
  assert list(torch_io.unwrap_state_dict({"model": "sav", "state_dict": sd})) == list(sd)
  # Only the leading module. goes (the official demo.py would remove both), and the leading
  # ones of a wrapped wrapper (the official loaders read those files too).
  assert list(torch_io.unwrap_state_dict(_tiny(["module.x.module.y"]))) == ["x.module.y"]
  assert list(torch_io.unwrap_state_dict(_tiny(["module.module.y"]))) == ["y"]


def test_unwrap_errors():
  with pytest.raises(CheckpointError, match="collides"):
    torch_io.unwrap_state_dict(_tiny(["module.a", "a"]), source="f.pth")
  with pytest.raises(CheckpointError, match=r"f\.pth.*'epoch'"):
    torch_io.unwrap_state_dict({"net": _tiny(["a"]), "epoch": 3}, source="f.pth")
  with pytest.raises(CheckpointError, match="no state dict found.*list"):
    torch_io.unwrap_state_dict([1, 2])
  with pytest.raises(CheckpointError, match="no state dict found"):
    torch_io.unwrap_state_dict({"model": {}})
  with pytest.raises(CheckpointError, match="'b': int"):
    torch_io.unwrap_state_dict({"a": np.zeros(2), "b": 3})
  with pytest.raises(CheckpointError, match=r"f\.pth: not a state dict of tensors: 1 of 2 "
                     r"entries .* e\.g\. 0: ndarray"):
    torch_io.unwrap_state_dict({"a": np.zeros(2), 0: np.zeros(2)}, source="f.pth")


def test_checkpoint_kind_from_manifests(fixtures_dir):
  sav = _manifest_keys(fixtures_dir, "sav_manifest.json")
  vda = _manifest_keys(fixtures_dir, "vda_vits_manifest.json")
  assert len(sav) == 494 and len(vda) == 351
  assert torch_io.checkpoint_kind(_tiny(sav)) == "sav"
  assert torch_io.checkpoint_kind(_tiny(vda)) == "vda"
  wrapped = {"model": _tiny("module." + k for k in sav), "optimizer": {}, "total_steps": 5}
  assert torch_io.checkpoint_kind(torch_io.unwrap_state_dict(wrapped)) == "sav"
  assert torch_io.checkpoint_kind(_tiny(k for k in sav if not k.startswith("depthnet."))) == "sav"
  # Without depthnet and corr_mlp its keys are under RAFT's three top-level names: still a
  # Stereo Any Video state dict, unless RAFT's own head is there.
  three = [k for k in sav if k.split(".")[0] in torch_io.RAFT_TOP_LEVEL]
  assert torch_io.checkpoint_kind(_tiny(three)) == "sav"
  assert torch_io.checkpoint_kind(_tiny(three + ["update_block.mask.0.weight"])) == "raft"
  assert torch_io.checkpoint_kind(_tiny(three + [torch_io.RAFT_SMALL_MARKER])) == "raft_small"


def test_a_file_of_another_kind_is_refused_with_the_callers_hint(tmp_path, fixtures_dir):
  vda = _manifest_keys(fixtures_dir, "vda_vits_manifest.json")
  np.savez(tmp_path / "vda.npz", **_tiny(vda))
  assert torch_io.load_state_dict_of_kind(tmp_path / "vda.npz", "vda").keys() == set(vda)
  with pytest.raises(CheckpointError) as e:
    torch_io.load_state_dict_of_kind(tmp_path / "vda.npz", "sav", {"vda": "add --vda"},
                                     label="SRC")
  assert str(e.value) == ("SRC is a Video Depth Anything (depth prior only) checkpoint, not a "
                          "Stereo Any Video one; add --vda")


def test_checkpoint_kind_errors(fixtures_dir):
  vda = _manifest_keys(fixtures_dir, "vda_vits_manifest.json")
  sav = _manifest_keys(fixtures_dir, "sav_manifest.json")
  cases = {
      "resnet": _tiny(["conv1.weight", "bn1.weight", "fc.bias"]),
      "vda_half": _tiny(k for k in vda if k.startswith("pretrained.")),
      "still_prefixed": _tiny("module." + k for k in sav),
      "depth_prior_only": _tiny(k for k in sav if k.startswith(("depthnet.", "corr_mlp."))),
  }
  for name, sd in cases.items():
    with pytest.raises(CheckpointError, match=r"unrecognised checkpoint layout: \d+ keys") as e:
      torch_io.checkpoint_kind(sd, source=name)
    assert name in str(e.value)
  for name, sd, extra in (("sav_plus_junk", _tiny(sav + ["extra.weight"]), "extra (1 key)"),
                          ("mixed", _tiny(sav[:3] + vda[:3]), "pretrained (3 keys)")):
    with pytest.raises(CheckpointError, match="a Stereo Any Video state dict with keys under "
                                              "other top-level names") as e:
      torch_io.checkpoint_kind(sd, source=name)
    assert str(e.value).startswith(f"{name}: ") and extra in str(e.value)
  with pytest.raises(CheckpointError, match="non-empty"):
    torch_io.checkpoint_kind({})


# --------------------------------------------------------------------------------------------
# Writing.

_SAVE_SD = {
    "a.weight": np.arange(6, dtype=np.float32).reshape(2, 3),
    "a.half": np.array([0.5, 1.5], np.float16),
    "a.index": np.array([[3, -4]], np.int64),
    "b.flag": np.array([True, False]),
    "b.u8": np.array([1, 2, 255], np.uint8),
    "b.scalar": np.array(2.5, np.float64),
    "c.t": np.arange(6, dtype=np.float32).reshape(2, 3).T,
}


@pytest.mark.parametrize("suffix", [".safetensors", ".npz"])
def test_save_load_round_trip(tmp_path, suffix):
  path = tmp_path / "sub" / f"w{suffix}"
  assert torch_io.save_state_dict(_SAVE_SD, path) == path
  out = torch_io.load_state_dict(path)
  assert set(out) == set(_SAVE_SD)
  for k, v in _SAVE_SD.items():
    assert out[k].dtype == v.dtype and out[k].shape == v.shape, k
    np.testing.assert_array_equal(out[k], v)
  assert sorted(os.listdir(path.parent)) == [path.name]  # no temporary files left
  umask = os.umask(0o027)
  try:  # created as open() creates files (0o666 less the umask), not 0o600 as mkstemp's
    torch_io.save_state_dict(_SAVE_SD, tmp_path / f"m{suffix}")
  finally:
    os.umask(umask)
  assert os.stat(tmp_path / f"m{suffix}").st_mode & 0o777 == 0o640
  with pytest.raises(FileExistsError, match="overwrite=True"):
    torch_io.save_state_dict({"x": np.zeros(1)}, path)
  torch_io.save_state_dict({"x": np.ones(2)}, path, overwrite=True)
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [1, 1])


def test_save_accepts_jax_arrays(tmp_path):
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  path = torch_io.save_state_dict({"x": jnp.arange(3.0)}, tmp_path / "j.safetensors")
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [0, 1, 2])


def test_safetensors_bfloat16_loads_as_float32(tmp_path):
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  import safetensors.numpy  # pylint: disable=import-outside-toplevel
  path = tmp_path / "bf.safetensors"
  safetensors.numpy.save_file({"x": np.array([1.5, -2], ml_dtypes.bfloat16)}, str(path))
  out = torch_io.load_state_dict(path)
  assert out["x"].dtype == np.float32
  np.testing.assert_array_equal(out["x"], [1.5, -2])
  assert torch_io.load_checkpoint_object(path)["x"].dtype == np.float32  # as documented


def test_safetensors_written_here_read_back_with_float8_widened(tmp_path):
  # safetensors' numpy reader cannot load F8 tensors: they are written as float32.
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  sd = {"f8": np.array([1.5, -2], ml_dtypes.float8_e4m3fn),
        "e5": np.array([1.5, -2], ml_dtypes.float8_e5m2),
        "bf": np.array([1.5, -2], ml_dtypes.bfloat16)}
  out = torch_io.load_state_dict(torch_io.save_state_dict(sd, tmp_path / "f8.safetensors"))
  assert out["f8"].dtype == out["e5"].dtype == out["bf"].dtype == np.float32
  np.testing.assert_array_equal(out["f8"], [1.5, -2])
  np.testing.assert_array_equal(out["e5"], [1.5, -2])


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
  def boom(*args, **kwargs):
    raise RuntimeError("disk full")

  monkeypatch.setattr(np, "savez", boom)
  with pytest.raises(RuntimeError, match="disk full"):
    torch_io.save_state_dict(_SAVE_SD, tmp_path / "w.npz")
  assert os.listdir(tmp_path) == []

  def full(*args, **kwargs):
    raise OSError(28, "No space left on device", "/the/temporary/file")

  monkeypatch.setattr(np, "savez", full)  # named by the destination, not the temporary file
  with pytest.raises(CheckpointError, match=r"w\.npz: could not write the file \(No space left "
                     r"on device\)$"):
    torch_io.save_state_dict(_SAVE_SD, tmp_path / "w.npz")
  assert os.listdir(tmp_path) == []


def test_save_errors(tmp_path):
  with pytest.raises(CheckpointError, match="use .safetensors, .npz"):
    torch_io.save_state_dict({"x": np.zeros(1)}, tmp_path / "w.h5")
  with pytest.raises(CheckpointError, match="cannot write 'a file without a suffix'"):
    torch_io.save_state_dict({"x": np.zeros(1)}, tmp_path / "weights")
  with pytest.raises(CheckpointError, match="keys must be strings"):
    torch_io.save_state_dict({1: np.zeros(1)}, tmp_path / "w.npz")


def test_save_npz_widens_bfloat16(tmp_path):
  # np.savez wrote bfloat16 as opaque 2-byte records, which read back as void arrays.
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  values = np.array([1.5, -2.0, 3.25], np.float32)
  path = torch_io.save_state_dict({"w": values.astype(ml_dtypes.bfloat16), "i": np.arange(2)},
                                  tmp_path / "w.npz")
  back = torch_io.load_state_dict(path)
  assert back["w"].dtype == np.float32 and back["i"].dtype == np.arange(2).dtype
  np.testing.assert_array_equal(back["w"], values)
  # float8_e5m2, which numpy sees as kind "f", was written as an unreadable '<f1'.
  for name in ("float8_e5m2", "float8_e4m3fn"):
    path = torch_io.save_state_dict({"w": values.astype(getattr(ml_dtypes, name))},
                                    tmp_path / f"{name}.npz")
    back = torch_io.load_state_dict(path)["w"]
    assert back.dtype == np.float32, name
    np.testing.assert_array_equal(back, values.astype(getattr(ml_dtypes, name)).astype(np.float32))


def test_save_pth_without_torch(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` fails, installed or not
  for suffix in (".pth", ".pt", ".bin"):  # each is written with torch.save
    with pytest.raises(CheckpointError, match=rf"writing \{suffix} needs torch.*\.safetensors or "
                       r"\.npz.*install torch"):
      torch_io.save_state_dict({"x": np.zeros(1)}, tmp_path / f"w{suffix}")
  assert os.listdir(tmp_path) == []


def test_save_pth_hands_torch_save_the_arrays_in_their_dtypes(tmp_path, monkeypatch):
  # The .pth writer runs without torch here: a stand-in `torch` records what torch.save gets.
  # bfloat16 and float8 arrays become tensors of the same torch dtype and bits; an ml_dtypes
  # type torch lacks is widened to float32; float32 arrays are copied, not shared.
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  saved = []

  class Dtype:
    def __init__(self, name, itemsize):
      self.name, self.itemsize = name, itemsize

  class Tensor:
    def __init__(self, array, dtype=None):
      self.array, self.dtype = array, dtype

    def view(self, dtype):
      return Tensor(self.array, dtype)

  torch = types.ModuleType("torch")
  torch.dtype, torch.bfloat16, torch.float8_e5m2 = Dtype, Dtype("bfloat16", 2), Dtype(
      "float8_e5m2", 1)
  torch.from_numpy = Tensor
  torch.save = lambda obj, fh: saved.append(obj)
  monkeypatch.setitem(sys.modules, "torch", torch)
  values = np.array([[0.5, -1.25], [3.0, 448.0]], np.float32)
  sd = {"f32": values, "bf16": values.astype(ml_dtypes.bfloat16),
        "f8": values.astype(ml_dtypes.float8_e5m2),  # numpy kind "f", unlike the others
        "e4m3": values.astype(ml_dtypes.float8_e4m3fn)}
  torch_io.save_state_dict(sd, tmp_path / "w.pth")
  (got,) = saved
  assert sorted(got) == sorted(sd) and (tmp_path / "w.pth").is_file()
  assert got["f32"].dtype is None and got["f32"].array.dtype == np.float32
  np.testing.assert_array_equal(got["f32"].array, values)
  assert not np.shares_memory(got["f32"].array, values)
  for key, dtype in (("bf16", torch.bfloat16), ("f8", torch.float8_e5m2)):
    assert got[key].dtype is dtype, key
    np.testing.assert_array_equal(got[key].array.view(sd[key].dtype), sd[key])  # same bits
  assert got["e4m3"].dtype is None and got["e4m3"].array.dtype == np.float32  # torch lacks it
  np.testing.assert_array_equal(got["e4m3"].array, sd["e4m3"].astype(np.float32))


# --------------------------------------------------------------------------------------------
# Dtype tables, rebuild-argument checks and storage views pinned one by one (gaps found by
# mutation testing: a wrong entry or a dropped check loaded wrong values silently, or a
# malformed file failed with an unrelated error).

# (torch dtype name as pickled by a v3 tensor, the little-endian numpy dtype its elements
# are by the format's definition, values a misreading would change: the sign bit set in
# unsigned ints, magnitudes beyond the narrower types).
_V3_DTYPES = (
    ("float64", "<f8", [1.5, -2.0 ** -1000]), ("float32", "<f4", [1.5, -3e38]),
    ("float16", "<f2", [0.5, -65504.0]), ("int64", "<i8", [2 ** 40, -3]),
    ("int32", "<i4", [2 ** 30, -7]), ("int16", "<i2", [-32768, 300]), ("int8", "i1", [-128, 5]),
    ("uint8", "u1", [255, 1]), ("uint16", "<u2", [65535, 300]),
    ("uint32", "<u4", [2 ** 32 - 1, 2 ** 31]), ("uint64", "<u8", [2 ** 64 - 1, 2 ** 63]),
    ("bool", "?", [True, False]), ("complex64", "<c8", [1 + 2j, -3.5j]),
    ("complex128", "<c16", [1e300 + 2j, -3.5j]),
    # torch's aliases (torch.float is torch.float32, torch.long is torch.int64, ...)
    ("float", "<f4", [1.5, -3e38]), ("double", "<f8", [1.5, -2.0 ** -1000]),
    ("half", "<f2", [0.5, -65504.0]), ("long", "<i8", [2 ** 40, -3]),
    ("int", "<i4", [2 ** 30, -7]), ("short", "<i2", [-32768, 300]),
    ("cfloat", "<c8", [1 + 2j, -3.5j]), ("cdouble", "<c16", [1e300 + 2j, -3.5j]),
)


@pytest.mark.parametrize("byteorder", ["little", "big"])
def test_v3_tensors_of_every_dtype_and_alias(tmp_path, fake_torch, byteorder):
  # Each v3 tensor reads its untyped storage's bytes as the dtype it names; the storage
  # offset (1) counts elements of that dtype. A big-endian file holds each element (each
  # part of a complex one) big-endian.
  b = _Builder(fake_torch)
  obj = {}
  for name, dtype, values in _V3_DTYPES:
    setattr(fake_torch, name, _FakeDType(name))
    elements = np.array([values[1]] + values, np.dtype(dtype))
    if byteorder == "big":
      elements = elements.astype(np.dtype(dtype).newbyteorder(">"))
    args = (b.untyped(elements.tobytes()), 1, (2,), (1,), False, collections.OrderedDict(),
            getattr(fake_torch, name))
    obj[name] = _Tensor(fake_torch._utils._rebuild_tensor_v3, args)
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "v3.pth", obj, byteorder=byteorder))
  for name, dtype, values in _V3_DTYPES:
    want = np.dtype(dtype).newbyteorder("=")
    assert sd[name].dtype == want and sd[name].dtype.isnative, name
    np.testing.assert_array_equal(sd[name], np.array(values, want), err_msg=name)


# torch storage class -> (its elements as numpy stores them, values, what the reader gives).
_STORAGE_CLASS_VALUES = {
    "DoubleStorage": ("<f8", [1.5, -2.0 ** -1000], None),
    "FloatStorage": ("<f4", [1.5, -3e38], None),
    "HalfStorage": ("<f2", [0.5, -65504.0], None),
    # bfloat16 is the high half of a float32: 0x3FC0 is 1.5, 0xC000 is -2.
    "BFloat16Storage": ("<u2", [0x3FC0, 0xC000], np.array([1.5, -2.0], np.float32)),
    "LongStorage": ("<i8", [2 ** 40, -3], None), "IntStorage": ("<i4", [2 ** 30, -7], None),
    "ShortStorage": ("<i2", [-32768, 300], None), "CharStorage": ("i1", [-128, 5], None),
    "ByteStorage": ("u1", [255, 1], None), "BoolStorage": ("?", [True, False], None),
    "ComplexFloatStorage": ("<c8", [1 + 2j, -3.5j], None),
    "ComplexDoubleStorage": ("<c16", [1e300 + 2j, -3.5j], None),
    "UntypedStorage": ("u1", [200, 1], None),  # bytes: uint8, as torch's untyped storage
}


@pytest.mark.parametrize("module", ["torch", "torch.cuda", "torch.storage"])
def test_v2_tensors_on_every_storage_class(tmp_path, fake_torch, monkeypatch, module):
  # A storage class names the dtype of a v2 tensor's elements, under `torch` (torch.save),
  # `torch.cuda` (a legacy file of GPU tensors) or `torch.storage`.
  if module != "torch":
    mod = types.ModuleType(module)
    monkeypatch.setitem(sys.modules, module, mod)
    setattr(fake_torch, module.split(".")[1], mod)
  else:
    mod = fake_torch
  b = _Builder(fake_torch)
  obj = {}
  for cls_name, (dtype, values, _) in _STORAGE_CLASS_VALUES.items():
    cls = type(cls_name, (), {"__module__": module})
    setattr(mod, cls_name, cls)
    key = str(len(b.storages))
    b.storages[key] = _Storage(key, cls, 2, np.array(values, dtype).tobytes())
    obj[cls_name] = _Tensor(fake_torch._utils._rebuild_tensor_v2,
                            (b.storages[key], 0, (2,), (1,), False, collections.OrderedDict()))
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "classes.pth", obj))
  for cls_name, (dtype, values, want) in _STORAGE_CLASS_VALUES.items():
    want = np.array(values, np.dtype(dtype).newbyteorder("=")) if want is None else want
    assert sd[cls_name].dtype == want.dtype, cls_name
    np.testing.assert_array_equal(sd[cls_name], want, err_msg=cls_name)


def test_every_allow_listed_tensor_form_is_read(tmp_path, fake_torch):
  # The forms torch.save writes beside plain v2 tensors: a Parameter with extra state
  # (`_rebuild_parameter_with_state`), a tensor subclass rebuilt by `_rebuild_from_type_v2`
  # with `torch.Tensor` (pickled as `torch Tensor`) or `torch.nn.parameter.Parameter`, and
  # torch.device objects kept in a checkpoint ("cuda:0", "cpu").
  utils = fake_torch._utils
  utils._rebuild_parameter_with_state = _fake_function("torch._utils",
                                                       "_rebuild_parameter_with_state")
  fake_torch.Tensor = type("Tensor", (), {"__module__": "torch"})
  fake_torch.device = _fake_function("torch", "device")
  parameter = sys.modules["torch.nn.parameter"].Parameter
  b = _Builder(fake_torch)
  st = b.storage(np.arange(6, dtype=np.float32), "float32")
  args = (st, 2, (2,), (1,), False, collections.OrderedDict())
  obj = {
      "model": {
          "with_state": _Tensor(utils._rebuild_parameter_with_state,
                                (_Tensor(utils._rebuild_tensor_v2, args), True,
                                 collections.OrderedDict(), {"extra": 1})),
          "tensor": _Tensor(fake_torch._tensor._rebuild_from_type_v2,
                            (utils._rebuild_tensor_v2, fake_torch.Tensor, args, {})),
          "parameter": _Tensor(fake_torch._tensor._rebuild_from_type_v2,
                               (utils._rebuild_tensor_v2, parameter, args, {})),
      },
      "devices": [_Tensor(fake_torch.device, ("cuda", 0)), _Tensor(fake_torch.device, ("cpu",))],
  }
  path = b.write_zip(tmp_path / "forms.pth", obj)
  out = torch_io.load_checkpoint_object(path)
  assert out["devices"] == ["cuda:0", "cpu"]
  for key in obj["model"]:
    np.testing.assert_array_equal(out["model"][key], [2, 3], err_msg=key)


def test_malformed_rebuild_arguments_are_refused_by_name(tmp_path, fake_torch):
  # Each argument a rebuild helper or allow-listed builtin gets is checked, and a bad one
  # refused with its own message (not an AttributeError or a numpy error from further on,
  # nor accepted: True as a size or offset, a set built from a string's characters, a
  # complex number parsed from text, any allow-listed function under _rebuild_from_type_v2).
  import codecs  # pylint: disable=import-outside-toplevel
  utils = fake_torch._utils
  from_type = fake_torch._tensor._rebuild_from_type_v2
  b = _Builder(fake_torch)
  st = b.storage(np.arange(6, dtype=np.float32), "float32")
  v2 = lambda *args: _Tensor(utils._rebuild_tensor_v2, args + (False, collections.OrderedDict()))
  good = (st, 0, (2,), (1,), False, collections.OrderedDict())
  cases = {
      "bool_size": (v2(st, 0, (True, 2), (2, 1)),
                    r"tensor size must be a tuple of non-negative ints, got \(True, 2\)"),
      "dict_size": (v2(st, 0, {2: 1}, (1,)), r"tensor size must be a tuple of non-negative"),
      "str_size": (v2(st, 0, "", ()), r"tensor size must be a tuple of non-negative ints, got ''"),
      "bool_offset": (v2(st, True, (2,), (1,)), r"bad tensor storage offset True"),
      "ranks": (v2(st, 0, (2, 3), (1,)), r"tensor size \(2, 3\) and stride \(1,\) differ in "
                                         r"length"),
      "no_storage": (v2([1.0, 2.0], 0, (2,), (1,)), r"tensor rebuilt from a list, not a storage"),
      "from_type_type": (_Tensor(from_type, (utils._rebuild_tensor_v2, st.cls, good, {})),
                         r"_rebuild_from_type_v2 for unsupported type TorchDType\(float32\)"),
      "from_type_fn": (_Tensor(from_type, (set, fake_torch._tensor.Tensor, ([1, 2],), {})),
                       r"_rebuild_from_type_v2 with unsupported function "
                       r"<safe (__builtin__|builtins)\.set>"),
      "from_type_codecs": (_Tensor(from_type, (codecs.encode, fake_torch._tensor.Tensor,
                                               ("a", "latin1"), {})),
                           r"_rebuild_from_type_v2 with unsupported function "
                           r"<safe _codecs\.encode>"),
      "from_type_dtype": (_Tensor(from_type, (fake_torch.float32, fake_torch._tensor.Tensor, good,
                                              {})),
                          r"_rebuild_from_type_v2 with unsupported function "
                          r"TorchDType\(float32\)"),
      "from_type_args": (_Tensor(from_type, (utils._rebuild_tensor_v2, fake_torch._tensor.Tensor,
                                             list(good), {})),
                         r"_rebuild_from_type_v2 needs an argument tuple"),
      "codecs": (_Evil(codecs.encode, 5, "latin1"), r"refused _codecs\.encode\(int, 'latin1'\)"),
      "set_of_str": (_Evil(set, "ab"), r"refused to build a set from a str"),
      "complex_of_str": (_Evil(complex, "1", "2"), r"refused complex\(\) of non-numbers"),
  }
  for name, (value, message) in cases.items():
    path = b.write_zip(tmp_path / f"{name}.pth", {"w": value})
    with pytest.raises(CheckpointError, match=rf"{name}\.pth: {message}"):
      torch_io.load_checkpoint_object(path)


def test_sets_and_frozensets_keep_their_type(tmp_path):
  # pickle protocol 2 writes both as a call of the builtin on a list: a frozenset read back
  # as a set compares equal to it (and then is mutable and unhashable).
  obj = {"s": {1, 2}, "f": frozenset([3, 4])}
  out = torch_io.load_checkpoint_object(_zip_with_pickle(tmp_path / "sets.pth",
                                                         pickle.dumps(obj, protocol=2)))
  assert type(out["s"]) is set and out["s"] == {1, 2}
  assert type(out["f"]) is frozenset and out["f"] == frozenset([3, 4])


def test_legacy_storage_of_no_listed_record_is_named(tmp_path, fake_torch):
  # A legacy file's object names a storage its key list leaves out: its data never comes.
  b = _Builder(fake_torch)
  st = b.storage(np.arange(3, dtype=np.float32), "float32")
  path = tmp_path / "unlisted.pth"
  path.write_bytes(_legacy_header() + b.pickle({"x": b.tensor(st, 0, (3,), (1,))}, legacy=True)
                   + pickle.dumps([], protocol=2))
  with pytest.raises(CheckpointError, match=r"unlisted\.pth: the data of storage '0' is "
                                            r"missing$"):
    torch_io.load_state_dict(path)


def test_pickle_bounds_at_their_limits(tmp_path, monkeypatch):
  # "More than MAX_PICKLE_OPS opcodes" and "a memo slot beyond the opcodes read so far",
  # exactly: PROTO, NONE, STOP is 3 opcodes; PROTO, EMPTY_DICT, BINPUT / LONG_BINPUT n is 3
  # opcodes when slot n is stored. The text PUT of protocol 0 is held to the same bound.
  path = _zip_with_pickle(tmp_path / "ops.pth", _pickle_with_ops(b"N"))
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_OPS", 3)
  assert torch_io.load_checkpoint_object(path) is None
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_OPS", 2)
  with pytest.raises(CheckpointError, match=r"ops\.pth: a pickle of more than 2 opcodes"):
    torch_io.load_checkpoint_object(path)
  monkeypatch.undo()
  for put, width in ((b"q", 1), (b"r", 4)):  # BINPUT, LONG_BINPUT
    for slot in (3, 4):
      path = _zip_with_pickle(tmp_path / f"memo{slot}_{width}.pth",
                              _pickle_with_ops(b"}" + put + slot.to_bytes(width, "little")))
      if slot == 3:
        assert torch_io.load_checkpoint_object(path) == {}
      else:
        with pytest.raises(CheckpointError, match=rf"memo4_{width}\.pth: the pickle stores into "
                                                  r"memo slot 4 after 3 opcodes"):
          torch_io.load_checkpoint_object(path)
  path = _zip_with_pickle(tmp_path / "text_put.pth", b"(dp4194304\n.")  # MARK DICT PUT STOP
  with pytest.raises(CheckpointError, match=r"text_put\.pth: the pickle stores into memo slot "
                                            r"4194304 after 3 opcodes"):
    torch_io.load_checkpoint_object(path)


def test_persistent_id_outside_the_object_pickle_is_refused(tmp_path):
  # In a legacy file only the object pickle names storages; a persistent id in its key
  # list (BINUNICODE 'a', BINPERSID) is refused by name, not failed on as corruption.
  path = tmp_path / "pid.pth"
  path.write_bytes(_legacy_header() + pickle.dumps({}, protocol=2)
                   + b"\x80\x02X\x01\x00\x00\x00aQ.")
  with pytest.raises(CheckpointError, match=r"pid\.pth: unexpected persistent id 'a'$"):
    torch_io.load_checkpoint_object(path)


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_empty_storage(tmp_path, fake_torch, fmt):
  # torch.zeros(0) is saved with a storage of 0 elements (an empty record): an empty array.
  b = _Builder(fake_torch)
  st = b.storage(np.zeros(0, np.float32), "float32")
  obj = {"e": b.tensor(st, 0, (0,), (1,)), "e2": b.tensor(st, 0, (0, 3), (3, 1))}
  path = tmp_path / "empty.pth"
  b.write_legacy(path, obj) if fmt == "legacy" else b.write_zip(path, obj)
  sd = torch_io.load_state_dict(path)
  assert sd["e"].shape == (0,) and sd["e2"].shape == (0, 3)
  assert sd["e"].dtype == sd["e2"].dtype == np.float32


def test_malformed_storage_ids_are_refused(tmp_path, fake_torch):
  # ('storage', <storage class>, <key: str>, <location>, <numel: int >= 0>): a negative
  # count read the whole record whatever it declared; an int key named a record all the
  # same; a storage type that is no torch class failed further on as corruption.
  b = _Builder(fake_torch)
  st = b.storage(np.arange(3, dtype=np.float32), "float32")
  body = {"x": b.tensor(st, 0, (2,), (1,))}
  for name, pid, message in (
      ("negative", ("storage", st.cls, "0", "cpu", -1), r"malformed storage id"),
      ("int_key", ("storage", st.cls, 0, "cpu", 3), r"malformed storage id"),
      ("str_type", ("storage", "FloatStorage", "0", "cpu", 3),
       r"storage type 'FloatStorage' is not a known torch storage")):
    path = _zip_with_pickle(tmp_path / f"{name}.pth", _with_storage_id(body, pid))
    with zipfile.ZipFile(path, "a") as zf:
      zf.writestr("archive/data/0", st.raw)
    with pytest.raises(CheckpointError, match=rf"{name}\.pth: {message}"):
      torch_io.load_state_dict(path)


def test_byteorder_record_with_a_line_end_is_read(tmp_path, fake_torch):
  # The record is compared without surrounding whitespace: "big\n" is big-endian.
  b = _Builder(fake_torch)
  path = b.write_zip(tmp_path / "nl.pth", {"w": b.array(np.array([1.5, -2.0], np.float32),
                                                        "float32")}, byteorder="big")
  with zipfile.ZipFile(path) as zf:
    records = {n: zf.read(n) for n in zf.namelist()}
  records["archive/byteorder"] = b"big\n"
  with zipfile.ZipFile(path, "w") as zf:
    for n, data in records.items():
      zf.writestr(n, data)
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["w"], [1.5, -2.0])


@pytest.mark.parametrize("names", [["a/data.pkl", "b/data.pkl"], ["a/b/data.pkl"],
                                   ["archive/xdata.pkl"]])
def test_zip_without_exactly_one_top_level_data_pkl_is_refused(tmp_path, names):
  # torch reads `<dir>/data.pkl` of the archive's one folder (or the root): two candidates
  # are ambiguous, a deeper one or another name ending in "data.pkl" is no checkpoint's.
  path = tmp_path / "which.pth"
  with zipfile.ZipFile(path, "w") as zf:
    for name in names:
      zf.writestr(name, pickle.dumps({}, protocol=2))
  with pytest.raises(CheckpointError, match=r"which\.pth: zip file without a single "
                                            r"'<dir>/data\.pkl' record"):
    torch_io.load_checkpoint_object(path)


def test_object_pickle_size_limit_is_inclusive(tmp_path, monkeypatch):
  # "Larger than MAX_PICKLE_BYTES" is refused: a data.pkl of exactly that many bytes is read.
  data = pickle.dumps({"a": 1}, protocol=2)
  path = _zip_with_pickle(tmp_path / "limit.pth", data)
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_BYTES", len(data))
  assert torch_io.load_checkpoint_object(path) == {"a": 1}
  monkeypatch.setattr(pickle_reader, "MAX_PICKLE_BYTES", len(data) - 1)
  with pytest.raises(CheckpointError, match=rf"limit\.pth: zip record 'archive/data\.pkl' is "
                                            rf"larger than {len(data) - 1} bytes"):
    torch_io.load_checkpoint_object(path)


def _zip_bytes(records, compression=zipfile.ZIP_DEFLATED):
  """An in-memory zip of `{name: (bytes, compress_type)}` records."""
  buf = io.BytesIO()
  with zipfile.ZipFile(buf, "w") as zf:
    for name, (data, how) in records.items():
      zf.writestr(name, data, compress_type=how)
  return zipfile.ZipFile(io.BytesIO(buf.getvalue()))


def test_inflation_bounds_at_their_limits(monkeypatch):
  # A compressed record inflating to FREE_INFLATION bytes is exempt, one byte more (from a
  # few bytes of deflated zeros) is refused; stored (uncompressed) records count neither
  # way, so a large stored record cannot cover compressed records beyond the total bound.
  monkeypatch.setattr(pickle_reader, "FREE_INFLATION", 10000)
  monkeypatch.setattr(pickle_reader, "FREE_TOTAL", 1 << 30)
  pickle_reader.check_inflation(_zip_bytes({"z": (bytes(10000), zipfile.ZIP_DEFLATED)}), "ok")
  with pytest.raises(CheckpointError, match=r"over: zip record 'z' inflates \d+ bytes to 10001 "):
    pickle_reader.check_inflation(_zip_bytes({"z": (bytes(10001), zipfile.ZIP_DEFLATED)}), "over")
  monkeypatch.setattr(pickle_reader, "FREE_TOTAL", 0)
  zeros = {f"z{i}": (bytes(10000), zipfile.ZIP_DEFLATED) for i in range(10)}  # ~30 B each
  stored = {"w": (np.random.default_rng(0).bytes(100000), zipfile.ZIP_STORED)}
  with pytest.raises(CheckpointError, match=r"total: its compressed zip records inflate \d+ "
                                            r"bytes to 100000 together"):
    pickle_reader.check_inflation(_zip_bytes({**stored, **zeros}), "total")
  pickle_reader.check_inflation(_zip_bytes(stored), "stored")  # stored only: nothing inflates
  # The total bound to the byte: FREE_TOTAL bytes beyond MAX_INFLATION x the compressed ones.
  monkeypatch.setattr(pickle_reader, "FREE_INFLATION", 1 << 30)
  zf = _zip_bytes(zeros)
  free = 100000 - pickle_reader.MAX_INFLATION * sum(i.compress_size for i in zf.infolist())
  monkeypatch.setattr(pickle_reader, "FREE_TOTAL", free)
  pickle_reader.check_inflation(zf, "at")
  monkeypatch.setattr(pickle_reader, "FREE_TOTAL", free - 1)
  with pytest.raises(CheckpointError, match=r"over: its compressed zip records inflate"):
    pickle_reader.check_inflation(zf, "over")


def test_inflation_takes_the_records_in_file_order(monkeypatch):
  # A central directory may list the records in any order: a record's bytes run to the
  # next record in the file, not to the next one listed (b listed first, a after it).
  monkeypatch.setattr(pickle_reader, "FREE_INFLATION", 1000)
  rng = np.random.default_rng(0)
  buf = io.BytesIO()
  with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
    zf.writestr("a", rng.bytes(5000))
    zf.writestr("b", rng.bytes(5000))  # random bytes: ~5000 deflated
    zf.filelist.reverse()  # the order the central directory is written in
  with zipfile.ZipFile(io.BytesIO(buf.getvalue())) as zf:
    assert [i.filename for i in zf.infolist()] == ["b", "a"]
    pickle_reader.check_inflation(zf, "reordered")


def _declare_in_central_directory(raw: bytes, sizes) -> bytes:
  """`raw` (a zip) with the central directory's compressed (+20) and uncompressed (+24)
  sizes of the records named in `sizes` ({name: (compressed or None, size or None)})
  replaced: the record headers a reader trusts."""
  raw = bytearray(raw)
  at = raw.find(b"PK\x01\x02")
  while at >= 0:
    name = bytes(raw[at + 46:at + 46 + int.from_bytes(raw[at + 28:at + 30], "little")]).decode()
    for field, value in zip((20, 24), sizes.get(name, (None, None))):
      if value is not None:
        raw[at + field:at + field + 4] = value.to_bytes(4, "little")
    at = raw.find(b"PK\x01\x02", at + 4)
  return bytes(raw)


def test_inflation_total_counts_the_bytes_records_occupy(monkeypatch):
  # Headers declaring 5000 compressed bytes for records of ~30 (deflated zeros) do not
  # raise the archive's allowance: the bound is on the bytes in the file.
  monkeypatch.setattr(pickle_reader, "FREE_TOTAL", 0)
  buf = io.BytesIO()
  with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
    for i in range(10):
      zf.writestr(f"z{i}", bytes(10000))
  raw = _declare_in_central_directory(buf.getvalue(), {f"z{i}": (5000, None) for i in range(10)})
  with zipfile.ZipFile(io.BytesIO(raw)) as zf:
    assert all(i.compress_size == 5000 for i in zf.infolist())
    with pytest.raises(CheckpointError, match=r"lie: its compressed zip records inflate \d{3} "
                                              r"bytes to 100000 together"):
      pickle_reader.check_inflation(zf, "lie")


def test_storage_record_shorter_than_its_header_declares(tmp_path, fake_torch):
  # A deflated record whose header declares 12 bytes but inflates to 8: the tensor's 3
  # elements are refused by name (not a numpy error on a short buffer).
  b = _Builder(fake_torch)
  obj = {"x": b.array(np.arange(3, dtype=np.float32), "float32")}
  buf = io.BytesIO()
  with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
    zf.writestr("archive/data.pkl", b.pickle(obj, legacy=False))
    zf.writestr("archive/data/0", b.storages["0"].raw[:8])
  path = tmp_path / "short.pth"
  path.write_bytes(_declare_in_central_directory(buf.getvalue(), {"archive/data/0": (None, 12)}))
  with pytest.raises(CheckpointError, match=r"short\.pth: storage 'archive/data/0' has 8 bytes, "
                                            r"needs 12$"):
    torch_io.load_state_dict(path)


def test_legacy_storage_key_lists_and_headers(tmp_path, fake_torch):
  # After the object pickle: a list of str keys, then per key an 8-byte count and the
  # elements. A key no tensor uses, the key of a view (its data is its base's), a key of
  # another type, a view named by a non-str key, and a count cut short are refused by name.
  b = _Builder(fake_torch)
  st = b.storage(np.arange(4, dtype=np.float32), "float32")
  path = tmp_path / "keys.pth"

  def write(keys, tail=struct.pack("<q", 4) + st.raw, view=None):
    pid = ("storage", st.cls, st.key, "cpu", st.numel, view)
    path.write_bytes(_legacy_header() + _with_storage_id({"x": b.tensor(st, 0, (2,), (1,))}, pid)
                     + pickle.dumps(keys, protocol=2) + tail)

  write(["0"])
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [0, 1])
  for keys, view, message in (
      (["0", "9"], None, r"storage '9' listed but never used by a tensor"),
      (["v"], ("v", 1, 2), r"storage 'v' listed but never used by a tensor"),
      ([0], None, r"malformed storage key list"),
      (("0",), None, r"malformed storage key list"),
      (["0"], ("v", 1), r"malformed storage view \('v', 1\)"),
      (["0"], (7, 1, 2), r"malformed storage view \(7, 1, 2\)")):
    write(keys, view=view)
    with pytest.raises(CheckpointError, match=rf"keys\.pth: {message}"):
      torch_io.load_state_dict(path)
  for tail in (b"", struct.pack("<q", 4)[:5]):  # the file ends in the count
    write(["0"], tail)
    with pytest.raises(CheckpointError, match=r"keys\.pth: truncated legacy checkpoint "
                                              r"\(storage '0'\)$"):
      torch_io.load_state_dict(path)


def test_float8_variants_are_widened_to_float32(tmp_path, fake_torch):
  # By the formats' definitions: e5m2 (bias 15) 0x3C = 1, 0xC0 = -2, 0x7B = 57344, 0x01 =
  # 2**-16; e4m3fnuz (bias 8) 0x40 = 1, 0xC8 = -2, 0x7F = 240, 0x01 = 2**-10; e5m2fnuz
  # (bias 16) 0x40 = 1, 0xC4 = -2, 0x7F = 57344, 0x01 = 2**-17.
  b = _Builder(fake_torch)
  cases = {"float8_e5m2": ([0x3C, 0xC0, 0x7B, 0x01], [1, -2, 57344, 2.0 ** -16]),
           "float8_e4m3fnuz": ([0x40, 0xC8, 0x7F, 0x01], [1, -2, 240, 2.0 ** -10]),
           "float8_e5m2fnuz": ([0x40, 0xC4, 0x7F, 0x01], [1, -2, 57344, 2.0 ** -17])}
  obj = {}
  for name, (bits, _) in cases.items():
    setattr(fake_torch, name, _FakeDType(name))
    args = (b.untyped(bytes(bits)), 0, (4,), (1,), False, collections.OrderedDict(),
            getattr(fake_torch, name))
    obj[name] = _Tensor(fake_torch._utils._rebuild_tensor_v3, args)
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "f8.pth", obj))
  for name, (_, values) in cases.items():
    assert sd[name].dtype == np.float32, name
    np.testing.assert_array_equal(sd[name], np.array(values, np.float32), err_msg=name)


def test_tensor_shape_limits(tmp_path, fake_torch):
  # A stride-0 expansion may have more elements than its storage (up to 2**24); a tensor
  # of more than 32 dimensions is refused; a v3 tensor on an untyped storage whose bytes
  # are no whole number of its elements is refused by name.
  b = _Builder(fake_torch)
  st = b.storage(np.array([1, 2, 3], np.float32), "float32")
  path = b.write_zip(tmp_path / "expand.pth", {"x": b.tensor(st, 0, (4, 3), (0, 1))})
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], [[1, 2, 3]] * 4)
  path = b.write_zip(tmp_path / "dims.pth", {"x": b.tensor(st, 0, (1,) * 33, (1,) * 33)})
  with pytest.raises(CheckpointError, match=r"dims\.pth: refused a tensor of size \(1, 1, "):
    torch_io.load_state_dict(path)
  path = b.write_zip(tmp_path / "dims32.pth", {"x": b.tensor(st, 0, (1,) * 32, (1,) * 32)})
  assert torch_io.load_state_dict(path)["x"].shape == (1,) * 32
  b = _Builder(fake_torch)
  args = (b.untyped(bytes(5)), 0, (1,), (1,), False, collections.OrderedDict(), fake_torch.float32)
  path = b.write_zip(tmp_path / "odd.pth", {"x": _Tensor(fake_torch._utils._rebuild_tensor_v3,
                                                         args)})
  with pytest.raises(CheckpointError, match=r"odd\.pth: storage size is not a multiple of "
                                            r"float32"):
    torch_io.load_state_dict(path)


def test_memory_budget_counts_output_bytes_and_view_roots(tmp_path, fake_torch, monkeypatch):
  # The tensors may take 4x the bytes of the storages they come from (no extra allowance
  # here): counted in the bytes of the arrays made (float32 for a bfloat16 or a v3 float32
  # tensor on an untyped storage, whatever the storage's element), up to the bound
  # inclusive; a legacy view's allowance is its base storage's.
  monkeypatch.setattr(pickle_reader, "_EXTRA_TENSOR_BYTES", 0)
  b = _Builder(fake_torch)
  bf = b.storage(np.ones(100, np.float32), "bfloat16")  # 200 bytes: 800 allowed
  for n, ok in ((2, True), (3, False)):  # 400 bytes each as float32
    b.write_zip(tmp_path / "bf.pth", {f"w{i}": b.tensor(bf, 0, (100,), (1,)) for i in range(n)})
    if ok:
      assert len(torch_io.load_state_dict(tmp_path / "bf.pth")) == n
    else:
      with pytest.raises(CheckpointError, match=r"bf\.pth: refused: its tensors would take"):
        torch_io.load_state_dict(tmp_path / "bf.pth")
  b = _Builder(fake_torch)
  raw = b.untyped(np.ones(100, np.float32).tobytes())  # 400 bytes: 1600 allowed
  v3 = lambda: _Tensor(fake_torch._utils._rebuild_tensor_v3,
                       (raw, 0, (100,), (1,), False, collections.OrderedDict(), fake_torch.float32))
  b.write_zip(tmp_path / "v3.pth", {f"w{i}": v3() for i in range(4)})
  assert len(torch_io.load_state_dict(tmp_path / "v3.pth")) == 4
  b.write_zip(tmp_path / "v3.pth", {f"w{i}": v3() for i in range(5)})
  with pytest.raises(CheckpointError, match=r"v3\.pth: refused: its tensors would take"):
    torch_io.load_state_dict(tmp_path / "v3.pth")
  b = _Builder(fake_torch)
  st = b.storage(np.arange(10, dtype=np.float32), "float32")  # 40 bytes: 160 allowed
  pid = ("storage", st.cls, st.key, "cpu", st.numel, ("view0", 2, 8))
  path = tmp_path / "view.pth"
  path.write_bytes(_legacy_header() + _with_storage_id({"x": b.tensor(st, 0, (8,), (1,))}, pid)
                   + pickle.dumps([st.key], protocol=2) + struct.pack("<q", 10) + st.raw)
  np.testing.assert_array_equal(torch_io.load_state_dict(path)["x"], np.arange(2, 10))
  # To the byte: 1-byte elements, 100 of storage allow 400; one element more is refused.
  b = _Builder(fake_torch)
  u8 = b.storage(np.zeros(100, np.uint8), "uint8")
  full = {f"w{i}": b.tensor(u8, 0, (100,), (1,)) for i in range(4)}
  assert len(torch_io.load_state_dict(b.write_zip(tmp_path / "u8.pth", full))) == 4
  b.write_zip(tmp_path / "u8.pth", {**full, "x": b.tensor(u8, 0, (1,), (1,))})
  with pytest.raises(CheckpointError, match=r"u8\.pth: refused: its tensors would take"):
    torch_io.load_state_dict(tmp_path / "u8.pth")


def test_empty_tensor_needs_no_storage_elements(tmp_path, fake_torch):
  # A tensor of no elements reads none, wherever its offset points (as torch's set_ takes
  # it): (0, 2) at offset 7 of a 6-element storage is an empty array, not an overrun.
  b = _Builder(fake_torch)
  st = b.storage(np.arange(6, dtype=np.float32), "float32")
  sd = torch_io.load_state_dict(b.write_zip(tmp_path / "e.pth",
                                            {"x": b.tensor(st, 7, (0, 2), (2, 1))}))
  assert sd["x"].shape == (0, 2) and sd["x"].dtype == np.float32


def test_files_are_told_by_suffix_in_any_case_and_by_content(tmp_path, fake_torch):
  # Suffixes are compared lower-cased (for reading and writing); `.ckpt` is a torch file; an
  # empty zip archive (only its end record, PK\x05\x06) is a zip without a checkpoint; a
  # pickle not starting with the legacy magic number is no torch file.
  b = _Builder(fake_torch)
  b.write_zip(tmp_path / "w.ckpt", {"w": b.array(np.array([1.5], np.float32), "float32")})
  np.testing.assert_array_equal(torch_io.load_state_dict(tmp_path / "w.ckpt")["w"], [1.5])
  torch_io.save_state_dict({"w": np.array([2.5], np.float32)}, tmp_path / "W.NPZ")
  with zipfile.ZipFile(tmp_path / "W.NPZ") as zf:
    assert zf.namelist() == ["w.npy"]
  np.testing.assert_array_equal(torch_io.load_state_dict(tmp_path / "W.NPZ")["w"], [2.5])
  (tmp_path / "empty.pth").write_bytes(b"PK\x05\x06" + bytes(18))
  with pytest.raises(CheckpointError, match=r"empty\.pth: zip file without a single"):
    torch_io.load_state_dict(tmp_path / "empty.pth")
  (tmp_path / "long.pth").write_bytes(b"L123L\n.")  # protocol 0: the long 123
  with pytest.raises(CheckpointError, match=r"long\.pth: not a torch checkpoint \(neither a zip "
                                            r"archive nor a legacy pickle"):
    torch_io.load_state_dict(tmp_path / "long.pth")


class _ArrayLike:
  """Converts to a numpy array like a JAX array (has `__array__` and `shape`)."""

  def __init__(self, array):
    self.array, self.shape = array, array.shape

  def __array__(self, dtype=None, copy=None):
    del copy
    return self.array if dtype is None else self.array.astype(dtype)


class _FakeTorchTensor:
  """Like a torch bfloat16 tensor: `.numpy()` refuses bfloat16, `.float()` converts."""

  __module__ = "torch"

  def __init__(self, values, dtype="torch.bfloat16"):
    self.values, self.dtype, self.shape = values, dtype, values.shape

  def __array__(self, dtype=None, copy=None):
    raise TypeError("not through __array__")

  def detach(self):
    return self

  def cpu(self):
    return self

  def float(self):
    return _FakeTorchTensor(self.values.astype(np.float32), "torch.float32")

  def numpy(self):
    if self.dtype != "torch.float32":
      raise TypeError(f"Got unsupported ScalarType {self.dtype}")
    return self.values


def test_unwrap_converts_array_likes_and_widens_bfloat16():
  # Values that are tensors of another library become numpy arrays; bfloat16 (ml_dtypes',
  # or torch's through .float()) becomes float32 with the same values.
  import ml_dtypes  # pylint: disable=import-outside-toplevel
  values = np.array([1.5, -2.0], np.float32)
  sd = torch_io.unwrap_state_dict({
      "np_bf16": values.astype(ml_dtypes.bfloat16),
      "like": _ArrayLike(values.astype(np.float16)),
      "like_bf16": _ArrayLike(values.astype(ml_dtypes.bfloat16)),
      "torch_bf16": _FakeTorchTensor(values.astype(ml_dtypes.bfloat16)),
  })
  assert sd["like"].dtype == np.float16 and isinstance(sd["like"], np.ndarray)
  for key in ("np_bf16", "like_bf16", "torch_bf16"):
    assert sd[key].dtype == np.float32, key
    np.testing.assert_array_equal(sd[key], values, err_msg=key)
  # "model" is the wrapper taken where a checkpoint has both.
  both = {"state_dict": {"b": np.zeros(1)}, "model": {"a": np.zeros(1)}}
  assert list(torch_io.unwrap_state_dict(both)) == ["a"]


def test_checkpoint_kind_markers_and_names():
  # RAFT is told by either marker, only when the keys are under RAFT's three names alone;
  # any of fnet, cnet, update_block with the model's other names is Stereo Any Video.
  kind = lambda keys: torch_io.checkpoint_kind(_tiny(keys))
  assert kind(["fnet.a", "cnet.b", "update_block.gru.convz1.weight"]) == "raft"
  assert kind(["fnet.a", "cnet.b", "update_block.mask.0.weight"]) == "raft"
  assert kind(["fnet.a", "depthnet.b", "update_block.mask.0.weight"]) == "sav"
  assert kind(["fnet.a", "depthnet.b", torch_io.RAFT_SMALL_MARKER]) == "sav"
  assert kind(["update_block.a", "depthnet.b"]) == "sav"


def test_callers_hint_replaces_the_default_one(tmp_path):
  np.savez(tmp_path / "raft.npz", **_tiny(["fnet.a", "cnet.b", "update_block.mask.0.weight"]))
  with pytest.raises(CheckpointError) as e:
    torch_io.load_state_dict_of_kind(tmp_path / "raft.npz", "sav", {"raft": "mine"}, label="R")
  assert str(e.value) == "R is a RAFT (optical flow) checkpoint, not a Stereo Any Video one; mine"


def test_expansion_limit_is_inclusive(tmp_path, fake_torch):
  # A stride-0 expansion may have up to 2**24 elements whatever its storage's size (one
  # uint8 here: a 16 MiB array); one more is refused.
  b = _Builder(fake_torch)
  st = b.storage(np.array([7], np.uint8), "uint8")
  path = b.write_zip(tmp_path / "x.pth", {"x": b.tensor(st, 0, (1 << 24,), (0,))})
  x = torch_io.load_state_dict(path)["x"]
  assert x.shape == (1 << 24,) and x[0] == x[-1] == 7
  del x
  b.write_zip(path, {"x": b.tensor(st, 0, ((1 << 24) + 1,), (0,))})
  with pytest.raises(CheckpointError, match=r"x\.pth: refused a tensor of size \(16777217,\) "
                                            r"built from a storage of 1 elements"):
    torch_io.load_state_dict(path)


@pytest.mark.parametrize("where", ["magic", "protocol", "sys_info", "keys"])
def test_legacy_header_pickles_get_no_placeholders(tmp_path, where):
  # opaque_unknown replaces refused globals in the object pickle only: one in the magic
  # number, protocol version, sys_info or storage key list pickle is refused all the same
  # (an ignored sys_info would otherwise let any object through unseen).
  marker = tmp_path / "pwned"
  evil = pickle.dumps(_Evil(os.system, f"touch {marker}"), protocol=2)
  parts = [pickle.dumps(x, protocol=2) for x in
           (pickle_reader.LEGACY_MAGIC, 1001, {"little_endian": True}, {"a": 1}, [])]
  parts[["magic", "protocol", "sys_info", "keys"].index(where) + (where == "keys")] = evil
  path = tmp_path / "header.pth"
  path.write_bytes(b"".join(parts))
  with pytest.raises(CheckpointError, match=r"header\.pth: .*refusing to load the pickled "
                                            r"global '(os|posix)\.system'"):
    torch_io.load_checkpoint_object(path, opaque_unknown=True)
  assert not marker.exists()


def test_ordered_dicts_become_plain_dicts(tmp_path):
  # As documented: OrderedDicts (torch's state dicts) come back as plain dicts, in order.
  obj = collections.OrderedDict([("b", 1), ("a", collections.OrderedDict([("y", 2), ("x", 3)]))])
  out = torch_io.load_checkpoint_object(_zip_with_pickle(tmp_path / "od.pth",
                                                         pickle.dumps(obj, protocol=2)))
  assert type(out) is dict and type(out["a"]) is dict
  assert list(out) == ["b", "a"] and list(out["a"].items()) == [("y", 2), ("x", 3)]


def test_npz_refusals_are_not_wrapped_as_read_errors(tmp_path):
  # The reader's own refusals of an .npz (not an archive, a bomb) are given as they are,
  # not wrapped as "cannot read .npz file (CheckpointError: ...)".
  np.save(tmp_path / "one.npy", np.zeros(3))
  (tmp_path / "one.npz").write_bytes((tmp_path / "one.npy").read_bytes())
  with pytest.raises(CheckpointError) as e:
    torch_io.load_state_dict(tmp_path / "one.npz")
  assert str(e.value) == f"{tmp_path / 'one.npz'}: not an .npz archive (a single .npy array)"
  np.savez_compressed(tmp_path / "bomb.npz", w=np.zeros(1 << 21, np.float32))  # 8 MiB of zeros
  with pytest.raises(CheckpointError) as e:
    torch_io.load_state_dict(tmp_path / "bomb.npz")
  assert str(e.value).startswith(f"{tmp_path / 'bomb.npz'}: zip record 'w.npy' inflates ")


def test_torch_size_of_a_list_is_a_tuple(tmp_path, fake_torch):
  # torch.Size is a tuple, whatever sequence its pickle calls it with.
  fake_torch.Size = _fake_function("torch", "Size")
  b = _Builder(fake_torch)
  out = torch_io.load_checkpoint_object(b.write_zip(tmp_path / "s.pth",
                                                    {"s": _Tensor(fake_torch.Size, ([2, 3],))}))
  assert type(out["s"]) is tuple and out["s"] == (2, 3)


def test_npz_with_two_records_of_one_name_is_refused(tmp_path):
  # NumPy took the last copy silently (here all zeros instead of the weights).
  path = tmp_path / "dup.npz"
  with pytest.warns(UserWarning, match="Duplicate name"):
    with zipfile.ZipFile(path, "w") as zf:
      for value in (np.ones(3, np.float32), np.zeros(3, np.float32)):
        buf = io.BytesIO()
        np.save(buf, value)
        zf.writestr("w.npy", buf.getvalue())
  with pytest.raises(CheckpointError, match=r"dup\.npz: zip file with records of the same name"):
    torch_io.load_state_dict(path)
  # `w` and `w.npy` are both the array `w` to NumPy (it took the last record silently).
  with zipfile.ZipFile(path, "w") as zf:
    for name, value in (("w.npy", np.ones(3, np.float32)), ("w", np.zeros(3, np.float32))):
      buf = io.BytesIO()
      np.save(buf, value)
      zf.writestr(name, buf.getvalue())
  with pytest.raises(CheckpointError, match=r"dup\.npz: zip file with records of the same name "
                                            r"\(\['w'\]\): which copy is the array\?"):
    torch_io.load_state_dict(path)
