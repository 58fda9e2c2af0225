"""Reading PyTorch checkpoint files without torch and without running pickled code.

PyTorch writes checkpoints with `pickle`. Unpickling an untrusted file can import and call
anything (`os.system`, `builtins.eval`, ...). This module never does that: the unpickler's
`find_class` only answers an explicit allow-list of names, and each allowed name is mapped to a
small function or marker of this module (nothing from torch is imported). Everything else
raises `CheckpointError`, or, when the caller asks for it, is answered by an inert
placeholder class (`OpaqueObject`) without the refused name ever being imported.

Two on-disk formats are supported:

* the zip format (torch >= 1.6): `<prefix>/data.pkl` holds the object pickle, whose persistent
  ids `('storage', StorageType, key, location, numel)` name the raw records
  `<prefix>/data/<key>`; an optional `<prefix>/byteorder` record says `little` or `big`;
* the legacy format (torch < 1.6, or `_use_new_zipfile_serialization=False`): pickles of the
  magic number, the protocol version (1001) and a `sys_info` dict, then the object pickle
  with persistent ids `('storage', StorageType, key, location, numel, view_metadata)`, then a
  pickled list of storage keys, then for each key an int64 element count followed by the raw
  little-endian elements.

Tensors are rebuilt as numpy arrays from (storage, offset, size, stride), so views,
transposes and tensors sharing one storage come out right; every array is a fresh copy.
bfloat16 and float8 tensors are converted to float32; other dtypes are kept.
"""

import collections
import contextlib
import io
import logging
import math
import os
import pickle
import pickletools
import struct
import zipfile

import numpy as np

log = logging.getLogger(__name__)

LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
LEGACY_PROTOCOL = 1001
# Tensors with more elements than their storage (stride-0 expansions) are refused above this.
_MAX_EXPANDED_NUMEL = 1 << 24
# All tensors together may take at most this many times their storages' bytes, plus
# `_EXTRA_TENSOR_BYTES` (tied weights and views copy a storage's elements; a small file of
# many full views of one storage, or of many expansions, would otherwise take any memory).
_MAX_TENSOR_TO_STORAGE = 4
_EXTRA_TENSOR_BYTES = 1 << 30
# A checkpoint's object pickle has a few opcodes per tensor (a training checkpoint with its
# optimizer state: ~10^5; one with a per-step log of 300k steps: ~2.4 million); each opcode
# may build an object, so their number bounds the memory the unpickler takes (~1 GB at
# most). Refused globals (`opaque_unknown`) each get a class: bounded too.
MAX_PICKLE_OPS = 1 << 24
MAX_REFUSED_GLOBALS = 1000


class CheckpointError(ValueError):
  """A checkpoint cannot be read, has an unexpected layout, or holds something refused."""


class RefusedGlobal(CheckpointError):
  """A pickle names a global that is not allowed (`global_name`, "module.name")."""

  def __init__(self, message: str, global_name: str):
    super().__init__(message)
    self.global_name = global_name


# torch dtype name -> little-endian numpy dtype of its raw storage elements.
_RAW_DTYPES = {
    "float64": "<f8", "float32": "<f4", "float16": "<f2", "bfloat16": "<u2",
    "int64": "<i8", "int32": "<i4", "int16": "<i2", "int8": "i1", "uint8": "u1",
    "uint16": "<u2", "uint32": "<u4", "uint64": "<u8", "bool": "?",
    "complex64": "<c8", "complex128": "<c16",
    "float8_e4m3fn": "u1", "float8_e5m2": "u1", "float8_e4m3fnuz": "u1",
    "float8_e5m2fnuz": "u1",
}
# Aliases under which torch dtypes can be pickled (`GLOBAL torch <name>`).
_DTYPE_ALIASES = {
    "float": "float32", "double": "float64", "half": "float16", "long": "int64",
    "int": "int32", "short": "int16", "cfloat": "complex64", "cdouble": "complex128",
}
_STORAGE_CLASSES = {
    "DoubleStorage": "float64", "FloatStorage": "float32", "HalfStorage": "float16",
    "BFloat16Storage": "bfloat16", "LongStorage": "int64", "IntStorage": "int32",
    "ShortStorage": "int16", "CharStorage": "int8", "ByteStorage": "uint8",
    "BoolStorage": "bool", "ComplexFloatStorage": "complex64",
    "ComplexDoubleStorage": "complex128", "UntypedStorage": "uint8",
}


class _Frozen:
  """Base of the objects the unpickler can reach: no `__dict__`, attributes set once.

  The pickle BUILD opcode can set attributes on any object on the unpickler's stack; freezing
  them keeps a malicious file from altering these objects (some are shared module globals).
  BUILD calls `__setstate__`: its slot state reaches `__setattr__` (refused, naming the
  attribute), any other state is refused as a BUILD of an object that takes no state (without
  it, a plain state dict failed only by accident, for want of a `__dict__`).
  """

  __slots__ = ()

  def __setattr__(self, name, value):
    raise CheckpointError(f"refused to set attribute {name!r} of {type(self).__name__}")

  def __setstate__(self, state):
    if (isinstance(state, tuple) and len(state) == 2 and state[0] is None
        and isinstance(state[1], dict)):
      for name, value in state[1].items():
        setattr(self, name, value)  # refused by __setattr__
    raise CheckpointError(
        f"refused the pickle BUILD opcode on a {type(self).__name__}: it takes no state "
        "(setting state on the reader's objects is not allowed in a checkpoint; the file may "
        "be malicious)")

  def _init(self, **attrs):
    for name, value in attrs.items():
      object.__setattr__(self, name, value)


class TorchDType(_Frozen):
  """Marker for a pickled `torch.<dtype>` or `torch.<X>Storage` class.

  Attributes:
    name: canonical torch dtype name, e.g. "float32".
    raw: numpy dtype of the raw little-endian storage elements.
  """

  __slots__ = ("name", "raw")

  def __init__(self, name: str):
    self._init(name=name, raw=np.dtype(_RAW_DTYPES[name]))

  def __repr__(self):
    return f"TorchDType({self.name})"


class OpaqueObject:
  """Inert stand-in for what a refused global builds (only with `opaque_unknown=True`).

  `find_class` answers each refused global with a fresh subclass of this class, so the
  pickle opcodes that call a global (REDUCE) or instantiate a class (NEWOBJ) give an
  `OpaqueObject` without running anything, and BUILD's state is discarded.
  """

  __slots__ = ()
  global_name = "?"

  def __new__(cls, *args, **kwargs):
    del args, kwargs
    return object.__new__(cls)

  def __init__(self, *args, **kwargs):
    del args, kwargs

  def __setstate__(self, state):
    del state

  @property
  def name(self):
    """`module.name` of the refused global."""
    return type(self).global_name

  def __repr__(self):
    return f"OpaqueObject({self.name})"


def _opaque_class(global_name):
  return type(f"Opaque[{global_name}]", (OpaqueObject,),
              {"__slots__": (), "global_name": global_name})


class _SafeFunction(_Frozen):
  """An allow-listed global: calls one of this module's rebuild helpers."""

  __slots__ = ("name", "fn")

  def __init__(self, name, fn):
    self._init(name=name, fn=fn)

  def __call__(self, *args, **kwargs):
    return self.fn(*args, **kwargs)

  def __repr__(self):
    return f"<safe {self.name}>"


class _TypeMarker(_Frozen):
  """Marker for the pickled classes `torch.Tensor` / `torch.nn.Parameter`."""

  __slots__ = ("name",)

  def __init__(self, name):
    self._init(name=name)


class _Storage(_Frozen):
  """A (possibly not yet read) storage: `numel` elements of `dtype`, or a view of a base.

  `data` (set once read) is a 1-D numpy array of `dtype.raw` in the byte order of the file.
  """

  __slots__ = ("key", "dtype", "numel", "base", "offset", "data", "big_endian")

  def __init__(self, key, dtype, numel, base=None, offset=0, big_endian=False):
    self._init(key=key, dtype=dtype, numel=numel, base=base, offset=offset, data=None,
               big_endian=big_endian)

  def set_data(self, data):
    object.__setattr__(self, "data", data)

  def array(self, source):
    """Returns the storage elements as a 1-D array of the raw dtype."""
    if self.base is not None:
      base = self.base.array(source)
      if self.offset + self.numel > base.size:
        raise CheckpointError(f"{source}: storage view {self.key} lies outside its base storage")
      return base[self.offset:self.offset + self.numel]
    if self.data is None:
      raise CheckpointError(f"{source}: the data of storage {self.key!r} is missing")
    return self.data


class _TensorRef(_Frozen):
  """A tensor to build once the storages are read: storage + offset/size/stride (elements).

  `dtype` overrides the storage dtype (`_rebuild_tensor_v3` on an untyped storage).
  """

  __slots__ = ("storage", "offset", "size", "stride", "dtype")

  def __init__(self, storage, offset, size, stride, dtype=None):
    self._init(storage=storage, offset=offset, size=size, stride=stride, dtype=dtype)


def _int_tuple(value, what):
  if not isinstance(value, (tuple, list)) or not all(
      isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value):
    raise CheckpointError(f"tensor {what} must be a tuple of non-negative ints, got {value!r}")
  return tuple(value)


def _tensor_ref(storage, offset, size, stride, dtype=None):
  if not isinstance(storage, _Storage):
    raise CheckpointError(f"tensor rebuilt from a {type(storage).__name__}, not a storage")
  if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
    raise CheckpointError(f"bad tensor storage offset {offset!r}")
  size, stride = _int_tuple(size, "size"), _int_tuple(stride, "stride")
  if len(size) != len(stride):
    raise CheckpointError(f"tensor size {size} and stride {stride} differ in length")
  return _TensorRef(storage, offset, size, stride, dtype)


def _rebuild_tensor(storage, storage_offset, size, stride):
  return _tensor_ref(storage, storage_offset, size, stride)


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False,
                       backward_hooks=None, metadata=None):
  del requires_grad, backward_hooks, metadata
  return _tensor_ref(storage, storage_offset, size, stride)


def _rebuild_tensor_v3(storage, storage_offset, size, stride, requires_grad=False,
                       backward_hooks=None, dtype=None, metadata=None):
  del requires_grad, backward_hooks, metadata
  if not isinstance(dtype, TorchDType):
    raise CheckpointError(f"_rebuild_tensor_v3 needs a torch dtype, got {dtype!r}")
  return _tensor_ref(storage, storage_offset, size, stride, dtype)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, state=None):
  del requires_grad, backward_hooks, state
  if not isinstance(data, _TensorRef):
    raise CheckpointError(f"parameter rebuilt from a {type(data).__name__}, not a tensor")
  return data


def _rebuild_from_type_v2(func, new_type, args, state=None):
  del state
  if not isinstance(new_type, _TypeMarker):
    raise CheckpointError(f"_rebuild_from_type_v2 for unsupported type {new_type!r}")
  if not isinstance(func, _SafeFunction) or func.fn not in _TENSOR_REBUILDERS:
    raise CheckpointError(f"_rebuild_from_type_v2 with unsupported function {func!r}")
  if not isinstance(args, tuple):
    raise CheckpointError("_rebuild_from_type_v2 needs an argument tuple")
  return func(*args)


def _codecs_encode(text, encoding="utf-8"):
  """Protocol-2 pickles store `bytes` as `_codecs.encode(str, 'latin1')`."""
  if not isinstance(text, str) or encoding not in ("latin1", "latin-1", "utf-8", "utf8"):
    raise CheckpointError(f"refused _codecs.encode({type(text).__name__}, {encoding!r})")
  return text.encode(encoding)


def _make_set(items=()):
  return set(_checked_iterable(items))


def _make_frozenset(items=()):
  return frozenset(_checked_iterable(items))


def _checked_iterable(items):
  if not isinstance(items, (list, tuple, set, frozenset)):
    raise CheckpointError(f"refused to build a set from a {type(items).__name__}")
  return items


def _make_complex(real=0.0, imag=0.0):
  if not all(isinstance(v, (int, float)) for v in (real, imag)):
    raise CheckpointError("refused complex() of non-numbers")
  return complex(real, imag)


def _torch_size(dims=()):
  return _int_tuple(dims, "torch.Size")


def _torch_device(*args):
  return ":".join(str(a) for a in args if isinstance(a, (str, int)))


_TENSOR_REBUILDERS = (_rebuild_tensor, _rebuild_tensor_v2, _rebuild_tensor_v3,
                      _rebuild_parameter)


def _safe_globals():
  """The allow-list: `(module, name)` -> this module's safe stand-in."""
  functions = {
      ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
      ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
      ("torch._utils", "_rebuild_tensor_v3"): _rebuild_tensor_v3,
      ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
      ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
      ("torch._tensor", "_rebuild_from_type_v2"): _rebuild_from_type_v2,
      ("torch", "Size"): _torch_size,
      ("torch", "device"): _torch_device,
      ("_codecs", "encode"): _codecs_encode,
  }
  for builtins_name in ("builtins", "__builtin__"):
    functions[(builtins_name, "set")] = _make_set
    functions[(builtins_name, "frozenset")] = _make_frozenset
    functions[(builtins_name, "complex")] = _make_complex
  table = {k: _SafeFunction(".".join(k), fn) for k, fn in functions.items()}
  table[("collections", "OrderedDict")] = collections.OrderedDict  # a C type: immutable
  for key in (("torch", "Tensor"), ("torch._tensor", "Tensor"),
              ("torch.nn.parameter", "Parameter")):
    table[key] = _TypeMarker(".".join(key))
  for name in list(_RAW_DTYPES) + list(_DTYPE_ALIASES):
    table[("torch", name)] = TorchDType(_DTYPE_ALIASES.get(name, name))
  for cls, dtype in _STORAGE_CLASSES.items():
    for module in ("torch", "torch.cuda", "torch.storage"):
      table[(module, cls)] = TorchDType(dtype)
  return table


SAFE_GLOBALS = _safe_globals()


class RestrictedUnpickler(pickle.Unpickler):
  """An unpickler that resolves only allow-listed globals and delegates storages.

  Args:
    file: binary file positioned at a pickle.
    source: file name used in error messages.
    persistent_load: callable turning a persistent id into a storage, or None to refuse.
    opaque_unknown: map refused globals to `OpaqueObject` instead of raising.
  """

  def __init__(self, file, source, persistent_load=None, opaque_unknown=False):
    super().__init__(file)
    self._source = source
    self._storage_loader = persistent_load
    self._opaque = opaque_unknown
    self.refused = {}  # "module.name" -> its placeholder class

  def find_class(self, module, name):
    obj = SAFE_GLOBALS.get((module, name))
    if obj is not None:
      return obj
    if self._opaque:
      key = f"{module}.{name}"
      if key not in self.refused:
        if len(self.refused) >= MAX_REFUSED_GLOBALS:
          raise CheckpointError(f"{self._source}: more than {MAX_REFUSED_GLOBALS} different "
                                "pickled globals: not a checkpoint")
        self.refused[key] = _opaque_class(key)
      return self.refused[key]
    raise RefusedGlobal(
        f"{self._source}: refusing to load the pickled global '{module}.{name}' (only tensor "
        "rebuild helpers and containers are allowed; the file may be malicious or hold "
        "pickled Python objects: load_state_dict(path, opaque_unknown=True) reads the "
        "weights beside such objects, replacing them by inert placeholders)",
        f"{module}.{name}")

  def persistent_load(self, pid):
    if self._storage_loader is None:
      raise CheckpointError(f"{self._source}: unexpected persistent id {pid!r}")
    return self._storage_loader(pid)


def check_pickle_ops(file, source) -> None:
  """Reads the next pickle of the seekable `file` opcode by opcode, without building anything,
  and goes back to where it began; raises CheckpointError when it has more than
  MAX_PICKLE_OPS opcodes or stores into a memo slot beyond the opcodes read so far (the C
  unpickler allocates the memo up to the largest index: one opcode of a 300-byte file asked
  for 4 GB)."""
  start = file.tell()
  count = 0
  for op, arg, _ in pickletools.genops(file):
    count += 1
    if count > MAX_PICKLE_OPS:
      raise CheckpointError(f"{source}: a pickle of more than {MAX_PICKLE_OPS} opcodes: not a "
                            "checkpoint's")
    if op.name in ("PUT", "BINPUT", "LONG_BINPUT") and arg > count:
      raise CheckpointError(f"{source}: the pickle stores into memo slot {arg} after "
                            f"{count} opcodes: not a checkpoint's pickle (it would allocate "
                            "a memo that large)")
  file.seek(start)


def _unpickle(file, source, persistent_load, opaque_unknown):
  """Runs one `RestrictedUnpickler`; every `CheckpointError` it raises names `source`."""
  check_pickle_ops(file, source)
  unpickler = RestrictedUnpickler(file, source, persistent_load, opaque_unknown)
  try:
    obj = unpickler.load()
  except CheckpointError as e:
    if str(e).startswith(source):
      raise
    raise CheckpointError(f"{source}: {e}") from e
  if unpickler.refused:
    log.warning("%s: replaced %d refused globals by inert placeholders: %s", source,
                len(unpickler.refused), ", ".join(sorted(unpickler.refused)))
  return obj


def _parse_storage_pid(pid, source, legacy):
  """Validates a storage persistent id; returns (dtype, key, numel, view_metadata)."""
  want = 6 if legacy else 5
  if not isinstance(pid, tuple) or not pid or pid[0] != "storage":
    kind = pid[0] if isinstance(pid, tuple) and pid else pid
    raise CheckpointError(f"{source}: unsupported persistent id {kind!r} (only storages; "
                          "files holding whole pickled nn.Modules are not supported)")
  if len(pid) != want:
    raise CheckpointError(f"{source}: malformed storage id {pid!r}")
  dtype, key, numel = pid[1], pid[2], pid[4]
  if not isinstance(dtype, TorchDType):
    raise CheckpointError(f"{source}: storage type {dtype!r} is not a known torch storage")
  if not isinstance(key, str) or not isinstance(numel, int) or numel < 0:
    raise CheckpointError(f"{source}: malformed storage id {pid!r}")
  return dtype, key, numel, (pid[5] if legacy else None)


@contextlib.contextmanager
def _reading(source, what):
  """Turns any error but `CheckpointError` into a `CheckpointError` naming the file."""
  try:
    yield
  except CheckpointError:
    raise
  except Exception as e:  # malformed pickles and archives raise many exception types
    raise CheckpointError(f"{source}: corrupt or truncated {what} ({type(e).__name__}: {e})") from e


def load_zip(path, source, opaque_unknown=False):
  """Loads the object of a torch zip-format checkpoint, tensors as `_TensorRef`s.

  Args:
    path: file path.
    source: name for error messages.
    opaque_unknown: see `RestrictedUnpickler`.

  Returns:
    The unpickled object; call `resolve_tensors` on it.
  """
  with _reading(source, "torch zip checkpoint"), zipfile.ZipFile(path) as zf:
    prefix = _zip_prefix(zf, source)
    check_inflation(zf, source)  # every record, before any is read
    order = "little"
    if prefix + "byteorder" in zf.namelist():
      order = _read_member(zf, prefix + "byteorder", 64, source).decode("ascii", "replace").strip()
    if order not in ("little", "big"):
      raise CheckpointError(f"{source}: unknown byteorder record {order!r}")
    storages = {}

    def load_storage(pid):
      dtype, key, numel, _ = _parse_storage_pid(pid, source, legacy=False)
      if key not in storages:
        storage = storages[key] = _Storage(key, dtype, numel, big_endian=order == "big")
        storage.set_data(_zip_record(zf, prefix, key, dtype, numel, order, source))
      return storages[key]

    pickled = io.BytesIO(_read_member(zf, prefix + "data.pkl", MAX_PICKLE_BYTES, source))
    return _unpickle(pickled, source, load_storage, opaque_unknown)


def check_unique_records(names, source, what: str) -> None:
  """A CheckpointError (ending in `what`) where a zip's record `names` repeat one: which
  copy would a reader take? (zipfile and NumPy: the last one; others: the first)"""
  twice = sorted(n for n, k in collections.Counter(names).items() if k > 1)
  if twice:
    raise CheckpointError(f"{source}: zip file with records of the same name ({twice[:3]}): "
                          f"{what}")


def _zip_prefix(zf, source):
  """The record prefix (`archive/`, `<stem>/`, ...) of the zip's single `data.pkl`.

  torch.save names the prefix after the file's stem, so `code.pth` holds `code/data.pkl`:
  a TorchScript archive is told by its `<prefix>code/` folder or `constants.pkl`.
  """
  all_names = zf.namelist()
  check_unique_records(all_names, source, "not a torch checkpoint")
  names = [n for n in all_names if n == "data.pkl" or n.endswith("/data.pkl")]
  names = [n for n in names if n.count("/") <= 1]
  prefix = names[0][:-len("data.pkl")] if len(names) == 1 else None
  if (any(n.startswith(prefix + "code/") or n == prefix + "constants.pkl" for n in all_names)
      if prefix is not None else any("/code/" in n or n.startswith("code/") for n in all_names)):
    raise CheckpointError(f"{source}: a TorchScript archive (torch.jit.save), not a "
                          "checkpoint; save the model's state_dict() instead")
  if prefix is None:
    raise CheckpointError(f"{source}: zip file without a single '<dir>/data.pkl' record; "
                          "not a torch checkpoint")
  return prefix


# The object pickle of a checkpoint is small (names, shapes, a scheduler's state): a larger
# one is no model checkpoint, and a compressed record must not inflate without bound.
MAX_PICKLE_BYTES = 1 << 28


def _read_member(zf, name: str, limit: int, source) -> bytes:
  """Zip member `name` (of an archive `check_inflation` passed), refused when it inflates to
  more than `limit` bytes."""
  with zf.open(name) as fh:
    data = fh.read(limit + 1)
  if len(data) > limit:
    raise CheckpointError(f"{source}: zip record {name!r} is larger than {limit} bytes: not "
                          "a model checkpoint's")
  return data


# A compressed zip record inflating more than this many times its compressed size is
# refused (weights deflate to ~0.9 of their size; an all-zero tensor to ~1/1000, so records
# up to FREE_INFLATION bytes are exempt): a 1 MB file cannot ask for more than ~100 MB per
# record. (The bytes read never exceed a record's declared size.) The records of one file
# together are held to the same ratio, with FREE_TOTAL bytes exempt.
MAX_INFLATION = 100
FREE_INFLATION = 1 << 20
FREE_TOTAL = 16 << 20


def check_inflation(zf: zipfile.ZipFile, source, what: str = "a checkpoint's weights",
                    why: str = "torch.save stores them uncompressed, and compressed weights "
                    "shrink little", error: type[Exception] = CheckpointError) -> None:
  """Raises `error` when a compressed record of the archive `zf`, or all of them together,
  inflate beyond MAX_INFLATION (a record is named): such an archive is not `what`, because
  `why`.

  A record's compressed size is taken as the bytes it occupies in the file (up to the next
  record or the central directory), not as its header declares: a crafted header declaring
  50x its real size passed a 1000x record. The records are also held to the bound together,
  whatever their order (a thousand records of 1 MiB of zeros each passed one by one).
  """
  infos = zf.infolist()
  starts = sorted({i.header_offset for i in infos})
  end = getattr(zf, "start_dir", None)
  if end is None:  # (CPython's ZipFile has it) the file's end
    end = zf.fp.seek(0, os.SEEK_END) if zf.fp is not None else math.inf
  following = dict(zip(starts, starts[1:] + [end]))
  inflated = compressed = 0
  for info in infos:
    if info.compress_type == zipfile.ZIP_STORED:
      continue
    packed = max(min(info.compress_size, following[info.header_offset] - info.header_offset), 0)
    if info.file_size > max(MAX_INFLATION * packed, FREE_INFLATION):
      raise error(f"{source}: zip record {info.filename!r} inflates {packed} bytes to "
                  f"{info.file_size} ({info.file_size / max(packed, 1):.0f}x, more than "
                  f"{MAX_INFLATION}x): not {what} ({why})")
    inflated += info.file_size
    compressed += packed
  if inflated > MAX_INFLATION * compressed + FREE_TOTAL:
    raise error(f"{source}: its compressed zip records inflate {compressed} bytes to "
                f"{inflated} together (more than {MAX_INFLATION}x): not {what}")


def _zip_record(zf, prefix, key, dtype, numel, order, source):
  name = f"{prefix}data/{key}"
  try:
    info = zf.getinfo(name)
  except KeyError:
    raise CheckpointError(f"{source}: storage record {name!r} is missing") from None
  nbytes = numel * dtype.raw.itemsize
  if info.file_size < nbytes:
    raise CheckpointError(f"{source}: storage {name!r} has {info.file_size} bytes, "
                          f"needs {nbytes}")
  # only the bytes the tensor needs: a compressed record may inflate far beyond them
  with zf.open(info) as fh:
    raw = fh.read(nbytes)
  if len(raw) < nbytes:
    raise CheckpointError(f"{source}: storage {name!r} has {len(raw)} bytes, needs {nbytes}")
  raw_dtype = dtype.raw.newbyteorder("<" if order == "little" else ">")
  return np.frombuffer(raw, dtype=raw_dtype, count=numel)


def load_legacy(fh, source, opaque_unknown=False):
  """Loads the object of a legacy (pre-1.6) torch checkpoint from an open binary file.

  Args:
    fh: seekable binary file at position 0.
    source: name for error messages.
    opaque_unknown: see `RestrictedUnpickler`.

  Returns:
    The unpickled object with tensors as `_TensorRef`s; call `resolve_tensors` on it.
  """
  with _reading(source, "legacy torch checkpoint"):
    try:
      magic = _unpickle(fh, source, None, False)
    except RefusedGlobal as e:  # a pickle of objects, not a torch file: no weights beside them
      raise CheckpointError(
          f"{source}: not a torch checkpoint: refusing to load the pickled global "
          f"'{e.global_name}' where a legacy torch file begins with its magic number (the "
          "file may be malicious; nothing in it was run)") from None
    if magic != LEGACY_MAGIC:
      raise CheckpointError(f"{source}: not a torch checkpoint (bad legacy magic number)")
    protocol = _unpickle(fh, source, None, False)
    if protocol != LEGACY_PROTOCOL:
      raise CheckpointError(f"{source}: unsupported legacy protocol version {protocol!r}")
    _unpickle(fh, source, None, False)  # sys_info; the data is always little-endian
    storages = {}
    obj = _unpickle(fh, source, _legacy_storage_loader(storages, source), opaque_unknown)
    keys = _unpickle(fh, source, None, False)
  if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
    raise CheckpointError(f"{source}: malformed storage key list")
  _read_legacy_storages(fh, keys, storages, source)
  return obj


def _legacy_storage_loader(storages, source):
  def load_storage(pid):
    dtype, key, numel, view = _parse_storage_pid(pid, source, legacy=True)
    if key not in storages:
      storages[key] = _Storage(key, dtype, numel)
    if view is None:
      return storages[key]
    if (not isinstance(view, tuple) or len(view) != 3 or not isinstance(view[0], str)
        or not all(isinstance(v, int) and v >= 0 for v in view[1:])):
      raise CheckpointError(f"{source}: malformed storage view {view!r}")
    view_key, offset, view_numel = view
    if view_key not in storages:
      storages[view_key] = _Storage(view_key, dtype, view_numel, storages[key], offset)
    return storages[view_key]
  return load_storage


def _read_legacy_storages(fh, keys, storages, source):
  remaining = os.fstat(fh.fileno()).st_size - fh.tell()
  for key in keys:
    storage = storages.get(key)
    if storage is None or storage.base is not None:
      raise CheckpointError(f"{source}: storage {key!r} listed but never used by a tensor")
    header = fh.read(8)
    if len(header) != 8:
      raise CheckpointError(f"{source}: truncated legacy checkpoint (storage {key!r})")
    (numel,) = struct.unpack("<q", header)
    nbytes = numel * storage.dtype.raw.itemsize
    if numel < storage.numel:  # (the message said "needs 48 bytes, 48 left")
      raise CheckpointError(f"{source}: corrupt legacy checkpoint (storage {key!r} holds "
                            f"{numel} elements, its persistent id declares {storage.numel})")
    if nbytes > remaining - 8:
      raise CheckpointError(f"{source}: truncated legacy checkpoint (storage {key!r} "
                            f"needs {nbytes} bytes, {max(remaining - 8, 0)} left)")
    raw = fh.read(nbytes)
    remaining -= 8 + nbytes
    storage.set_data(np.frombuffer(raw, dtype=storage.dtype.raw, count=numel))


def _materialize(ref, source, charge=lambda ref: None):
  """Builds a contiguous numpy array (a copy) from a `_TensorRef`; `charge(ref)` is called
  (and may raise) before the copy is made."""
  data = ref.storage.array(source)
  dtype = ref.dtype or ref.storage.dtype
  if dtype.raw != data.dtype.newbyteorder("<"):  # _rebuild_tensor_v3 on another storage type
    data = np.ascontiguousarray(data).view(np.uint8)
    if data.size % dtype.raw.itemsize:
      raise CheckpointError(f"{source}: storage size is not a multiple of {dtype.name}")
    data = data.view(dtype.raw.newbyteorder(">" if ref.storage.big_endian else "<"))
  numel = math.prod(ref.size)
  if numel > max(data.size, _MAX_EXPANDED_NUMEL) or len(ref.size) > 32:
    raise CheckpointError(f"{source}: refused a tensor of size {ref.size} built from a storage "
                          f"of {data.size} elements")
  charge(ref)
  if numel == 0:
    arr = np.zeros(ref.size, dtype=data.dtype)
  else:
    last = ref.offset + sum((n - 1) * s for n, s in zip(ref.size, ref.stride))
    if last >= data.size:
      raise CheckpointError(f"{source}: tensor of size {ref.size}, stride {ref.stride}, "
                            f"offset {ref.offset} overruns its storage of {data.size} elements")
    item = data.dtype.itemsize
    arr = np.lib.stride_tricks.as_strided(
        data[ref.offset:], shape=ref.size, strides=[s * item for s in ref.stride],
        writeable=False)
  arr = np.array(arr, dtype=data.dtype.newbyteorder("="), order="C")
  return _to_numpy_dtype(arr, dtype.name)


def _to_numpy_dtype(arr, name):
  """Converts raw bfloat16 (uint16 bits) and float8 (uint8 bits) arrays to float32."""
  if name == "bfloat16":
    return (arr.astype(np.uint32) << 16).view(np.float32)
  if name.startswith("float8"):
    import ml_dtypes  # pylint: disable=import-outside-toplevel
    return arr.view(getattr(ml_dtypes, name)).astype(np.float32)
  return arr


def resolve_tensors(obj, source):
  """Replaces every `_TensorRef` in a nested structure by a numpy array.

  Dicts (including OrderedDicts) become plain dicts, lists stay lists, tuples stay tuples.
  Shared sub-objects stay shared. Attributes set on pickled dicts (torch's `_metadata`) are
  dropped.

  Args:
    obj: the unpickled object.
    source: name for error messages.

  Returns:
    The structure with arrays.
  """
  memo = {}
  storages = set()
  budget = [_EXTRA_TENSOR_BYTES, 0]  # bytes allowed, bytes built

  def charge(ref):
    root = ref.storage
    while root.base is not None:
      root = root.base
    if id(root) not in storages and root.data is not None:
      storages.add(id(root))
      budget[0] += _MAX_TENSOR_TO_STORAGE * root.data.nbytes
    dtype = ref.dtype or ref.storage.dtype
    widened = dtype.name == "bfloat16" or dtype.name.startswith("float8")  # -> float32
    itemsize = 4 if widened else dtype.raw.itemsize
    budget[1] += math.prod(ref.size) * itemsize
    if budget[1] > budget[0]:
      raise CheckpointError(
          f"{source}: refused: its tensors would take over {budget[1] / 2**20:.1f} MiB, more "
          f"than {_MAX_TENSOR_TO_STORAGE}x the data the file holds (+"
          f"{_EXTRA_TENSOR_BYTES / 2**20:.0f} MiB); not a plain state dict")

  def walk(x):
    if id(x) in memo:
      if memo[id(x)] is None:
        raise CheckpointError(f"{source}: self-referencing tuple in the checkpoint")
      return memo[id(x)]
    if isinstance(x, _TensorRef):
      memo[id(x)] = _materialize(x, source, charge)
    elif isinstance(x, dict):
      memo[id(x)] = out = {}
      for k, v in x.items():
        out[walk(k)] = walk(v)
    elif isinstance(x, list):
      memo[id(x)] = out = []
      out.extend(walk(v) for v in x)
    elif isinstance(x, tuple):
      memo[id(x)] = None
      memo[id(x)] = tuple(walk(v) for v in x)
    else:
      return x
    return memo[id(x)]

  with _reading(source, "checkpoint structure"):
    return walk(obj)
