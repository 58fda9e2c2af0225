"""Loading and saving state dicts: PyTorch `.pth`/`.pt`/`.bin`, `.npz` and `.safetensors`.

`load_state_dict(path)` returns `{name: np.ndarray}` for any supported file, without torch
and without ever executing pickled code (see `pickle_reader`). `load_checkpoint_object` gives
the whole unpickled object (training checkpoints with optimizer state etc.),
`unwrap_state_dict` finds the model weights in it and `checkpoint_kind` tells a Stereo Any
Video state dict from a standalone Video Depth Anything one. `save_state_dict` writes
`.safetensors` / `.npz` (and `.pth` when torch happens to be installed) atomically.
"""

import logging
import os
import pathlib
import uuid
import zipfile
from typing import Mapping

import numpy as np

from sav_jax._checks import plural, widened
from sav_jax.convert.pickle_reader import LEGACY_MAGIC, CheckpointError, check_inflation
from sav_jax.convert.pickle_reader import check_unique_records
from sav_jax.convert.pickle_reader import load_legacy
from sav_jax.convert.pickle_reader import load_zip
from sav_jax.convert.pickle_reader import resolve_tensors

__all__ = [
    "CheckpointError", "TORCH_SUFFIXES", "load_checkpoint_object", "load_state_dict",
    "unwrap_state_dict", "checkpoint_kind", "save_state_dict",
]

log = logging.getLogger(__name__)

TORCH_SUFFIXES = (".pth", ".pt", ".bin", ".ckpt", ".tar")
_WRAPPER_KEYS = ("model", "state_dict")
_MODULE_PREFIX = "module."
# Top-level submodule names of the two layouts (sav_manifest.json, vda_vits_manifest.json).
SAV_TOP_LEVEL = frozenset({"fnet", "cnet", "update_block", "depthnet", "corr_mlp"})
VDA_TOP_LEVEL = frozenset({"pretrained", "head"})
# RAFT (the evaluator's optical flow) has three of the stereo model's names and this head.
RAFT_TOP_LEVEL = frozenset({"fnet", "cnet", "update_block"})
RAFT_MARKERS = ("update_block.mask.0.weight", "update_block.gru.convz1.weight")
RAFT_SMALL_MARKER = "update_block.gru.convz.weight"  # raft-small.pth's ConvGRU (no mask)


def _check_file(path):
  path = pathlib.Path(path)
  if not path.exists():
    raise CheckpointError(f"{path}: checkpoint file not found")
  if not path.is_file():
    raise CheckpointError(f"{path}: not a regular file")
  return path


def load_checkpoint_object(path, *, opaque_unknown: bool = False):
  """Loads a whole checkpoint as nested Python containers with numpy arrays for tensors.

  Torch files (`.pth`, `.pt`, `.bin`, `.ckpt`, `.tar`) are recognised by content: the zip
  format of torch >= 1.6 or the legacy pickle format. Nothing in them is executed: only
  tensor rebuild helpers and plain containers are allowed (see `pickle_reader`). `.npz` and
  `.safetensors` files give a flat `{name: array}` dict.

  Args:
    path: checkpoint file.
    opaque_unknown: instead of refusing a pickled global outside the allow-list, put an inert
      `pickle_reader.OpaqueObject` in its place (it is never imported or called). This lets
      the weights be read from training checkpoints whose scheduler or optimizer state holds
      pickled Python objects. The default refuses them.

  Returns:
    The checkpoint object: dicts (OrderedDicts become dicts), lists, tuples, scalars and
    numpy arrays. bfloat16 (and, in torch files, float8) tensors come back as float32, other
    dtypes unchanged; safetensors' reader cannot load float8 (F8) tensors at all.

  Raises:
    CheckpointError: missing, unreadable, truncated or malicious file, or unknown suffix.
  """
  path = _check_file(path)
  suffix = path.suffix.lower()
  if suffix == ".npz":
    return _load_npz(path)
  if suffix == ".safetensors":
    return _load_safetensors(path)
  if suffix not in TORCH_SUFFIXES:
    raise CheckpointError(f"{path}: unknown checkpoint suffix {suffix!r}; expected one of "
                          f"{', '.join(TORCH_SUFFIXES + ('.npz', '.safetensors'))}")
  return _load_torch(path, opaque_unknown)


def _load_torch(path, opaque_unknown):
  source = str(path)
  with open(path, "rb") as fh:
    head = fh.read(512)
    fh.seek(0)
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
      obj = load_zip(path, source, opaque_unknown)
    elif len(head) >= 262 and head[257:262] == b"ustar":
      raise CheckpointError(f"{source}: the pre-0.4 tar checkpoint format is not supported; "
                            "re-save it with a recent torch")
    elif head[:1] == b"\x80" or head.startswith(b"L%d" % LEGACY_MAGIC):  # protocol 2+ / 0-1
      obj = load_legacy(fh, source, opaque_unknown)
    elif not head:
      raise CheckpointError(f"{source}: empty file")
    else:
      raise CheckpointError(f"{source}: not a torch checkpoint (neither a zip archive nor a "
                            f"legacy pickle; starts with {head[:8]!r})")
  return resolve_tensors(obj, source)


def _load_npz(path):
  member = None
  try:
    with open(path, "rb") as fh:
      magic = fh.read(6)
    if magic == b"\x93NUMPY":
      raise CheckpointError(f"{path}: not an .npz archive (a single .npy array)")
    if not magic.startswith(b"PK"):  # NumPy would call it pickled data
      raise CheckpointError(f"{path}: not an .npz archive (an .npz file is a zip archive; "
                            f"this one starts with {magic!r})")
    with zipfile.ZipFile(path) as zf:  # before NumPy inflates a record
      check_inflation(zf, path)
      # (NumPy names `a.npy` and `a` both `a`, and would silently take the last copy)
      check_unique_records([n[:-4] if n.endswith(".npy") else n for n in zf.namelist()],
                           path, "which copy is the array?")
    with np.load(path, allow_pickle=False) as data:
      out = {}
      for member in data.files:
        out[member] = np.array(data[member])
      return out
  except Exception as e:  # pylint: disable=broad-except  # zlib.error, LZMAError, ... too
    if isinstance(e, CheckpointError):
      raise
    where = f" (array {member!r})" if member is not None else ""
    what = ("declares an array too large to read: corrupt?" if isinstance(e, MemoryError)
            else "cannot read .npz file")
    raise CheckpointError(f"{path}: {what}{where} ({type(e).__name__}: {e})") from e


def _load_safetensors(path):
  import safetensors.numpy  # pylint: disable=import-outside-toplevel
  try:
    data = safetensors.numpy.load_file(str(path))
  except Exception as e:  # the rust extension raises its own error type
    raise CheckpointError(f"{path}: cannot read .safetensors file ({type(e).__name__}: {e})"
                         ) from e
  out = {}
  for k, v in data.items():
    v = np.array(v)
    # (ml_dtypes' bfloat16 and float8 are of kind "V" too)
    out[k] = v.astype(np.float32) if v.dtype.kind == "V" else v
  return out


def load_state_dict(path, *, opaque_unknown: bool = False) -> dict:
  """Loads the model weights of a checkpoint as `{name: np.ndarray}`.

  `load_checkpoint_object` followed by `unwrap_state_dict`: wrappers (`{"model": ...}`,
  `{"state_dict": ...}`) are removed and a leading `module.` is stripped.

  Args:
    path: `.pth` / `.pt` / `.bin` / `.ckpt` / `.tar` (torch, zip or legacy format), `.npz`
      or `.safetensors` file.
    opaque_unknown: see `load_checkpoint_object`.

  Returns:
    A flat dict of numpy arrays, in file order.

  Raises:
    CheckpointError: the file cannot be read or holds no recognisable state dict.
  """
  obj = load_checkpoint_object(path, opaque_unknown=opaque_unknown)
  return unwrap_state_dict(obj, source=str(path))


def _is_tensor(v) -> bool:
  """A numpy array, or an array-like with a shape (a torch or JAX tensor, ...)."""
  return isinstance(v, np.ndarray) or (hasattr(v, "__array__") and hasattr(v, "shape"))


def _is_array_dict(obj):
  return bool(obj) and all(_is_tensor(v) for v in obj.values())


def _describe(obj):
  if isinstance(obj, Mapping):
    keys = list(obj)
    return f"a dict with {plural(len(keys), 'key')}, starting {keys[:5]!r}"
  return f"a {type(obj).__name__}"


def unwrap_state_dict(obj, source: str = "<checkpoint>") -> dict:
  """Finds the flat state dict in a loaded checkpoint object.

  Accepted forms: a raw `{name: array}` mapping (numpy arrays, or tensors that convert to
  them: torch's, JAX's); `{"model": sd, ...}` (training checkpoints
  also hold `optimizer`, `scheduler`, `total_steps`: ignored); `{"state_dict": sd, ...}`;
  these wrappers may nest. A leading `module.` (from `DataParallel`; `module.module.` from a
  wrapped wrapper) is then stripped from each key that has one. Unlike the official
  `demo.py`, which applies `k.replace("module.", "")` and so removes *every* occurrence,
  only the leading prefixes are removed, so a submodule whose name contains `module.` keeps
  it.

  Args:
    obj: what `load_checkpoint_object` returned.
    source: file name for error messages.

  Returns:
    `{name: np.ndarray}`.

  Raises:
    CheckpointError: no state dict found, non-string keys, non-array values, or two keys
      that become equal after stripping `module.`.
  """
  sd = obj
  for _ in range(4):
    if not isinstance(sd, Mapping) or _is_array_dict(sd):
      break
    wrapper = next((k for k in _WRAPPER_KEYS if isinstance(sd.get(k), Mapping)), None)
    if wrapper is None:
      break
    sd = sd[wrapper]
  if not isinstance(sd, Mapping) or not sd:
    raise CheckpointError(f"{source}: no state dict found; the checkpoint is {_describe(obj)}")
  sd = {k: _to_numpy(k, v, source) if _is_tensor(v) else v for k, v in sd.items()}
  bad = [(k, v) for k, v in sd.items() if not isinstance(k, str) or not isinstance(v, np.ndarray)]
  if bad:
    k, v = bad[0]
    raise CheckpointError(
        f"{source}: not a state dict of tensors: {len(bad)} of {len(sd)} entries are not "
        f"(str, tensor) pairs, e.g. {k!r}: {type(v).__name__}; the checkpoint is "
        f"{_describe(obj)} (expected a raw state dict or one wrapped under 'model' or "
        "'state_dict')")
  return _strip_module_prefix(sd, source)


# torch dtypes numpy has no type for; their values are exact in float32.
_TORCH_WIDENED = ("bfloat16", "float8_e4m3fn", "float8_e5m2", "float8_e4m3fnuz", "float8_e5m2fnuz")


def _to_numpy(key, v, source) -> np.ndarray:
  """`v` as a NumPy array; bfloat16 and float8 (torch's, or ml_dtypes' of JAX and NumPy
  arrays) widened to float32 exactly, as the file readers give them."""
  if isinstance(v, np.ndarray):
    return widened(v)
  try:
    if type(v).__module__.split(".")[0] == "torch" and hasattr(v, "detach"):
      # What torch.load gives: tensors that may require grad, live on a GPU or be bfloat16
      # (numpy takes none of them as they are).
      v = v.detach().cpu()
      if str(v.dtype).removeprefix("torch.") in _TORCH_WIDENED:
        v = v.float()
      return v.numpy()
    return widened(np.asarray(v))
  except (TypeError, RuntimeError) as e:
    raise CheckpointError(f"{source}: {key!r} ({type(v).__name__} of dtype "
                          f"{getattr(v, 'dtype', '?')}) does not convert to a numpy array: {e}; "
                          "convert it first (for torch: .detach().float())") from e


def _strip_module_prefix(sd, source):
  out = {}
  for k, v in sd.items():
    name = k
    while name.startswith(_MODULE_PREFIX):
      name = name[len(_MODULE_PREFIX):]
    if name in out:
      raise CheckpointError(f"{source}: key {k!r} collides with {name!r} once the leading "
                            "'module.' is stripped")
    out[name] = v
  return out


def checkpoint_kind(sd: dict, source: str = "<state dict>") -> str:
  """Tells which model a flat (unwrapped) state dict belongs to.

  Args:
    sd: `{name: array}` with any `module.` prefix already removed.
    source: file name for error messages.

  Returns:
    "sav" for a full Stereo Any Video state dict (`fnet.*`, `cnet.*`, `update_block.*`,
    `corr_mlp.*`, `depthnet.*` including `depthnet.depthanything.*`), or "vda" for a
    standalone Video Depth Anything file (flat `pretrained.*` and `head.*` keys), or "raft"
    for the evaluator's RAFT optical-flow model (`fnet.*`, `cnet.*`, `update_block.*` with
    `update_block.mask.0.weight` or RAFT's separable GRU), or "raft_small" for the small
    RAFT (`raft-small.pth`: a plain ConvGRU, no mask), which is not supported.

  Raises:
    CheckpointError: the keys match neither layout (the message lists what was found).
  """
  if not isinstance(sd, dict) or not sd:
    raise CheckpointError(f"{source}: expected a non-empty state dict, got {_describe(sd)}")
  tops = {}
  for k in sd:
    top = str(k).split(".", 1)[0]
    tops[top] = tops.get(top, 0) + 1
  sav_like = tops.keys() & {"fnet", "cnet", "update_block"}
  if set(tops) == RAFT_TOP_LEVEL and RAFT_SMALL_MARKER in sd:
    return "raft_small"
  if set(tops) == RAFT_TOP_LEVEL and any(k in sd for k in RAFT_MARKERS):
    return "raft"
  if set(tops) <= SAV_TOP_LEVEL and sav_like:
    return "sav"
  if set(tops) == VDA_TOP_LEVEL:
    return "vda"
  if sav_like:  # a Stereo Any Video state dict with other things in it
    extra = sorted(set(tops) - SAV_TOP_LEVEL)
    first = next(k for k in sd if str(k).split(".", 1)[0] in extra)
    counts = ", ".join(f"{t} ({plural(tops[t], 'key')})" for t in extra)
    raise CheckpointError(
        f"{source}: a Stereo Any Video state dict with keys under other top-level names: "
        f"{counts}, e.g. {first!r}; the model's "
        f"are {', '.join(sorted(SAV_TOP_LEVEL))} (remove the others)")
  keys = list(sd)
  raise CheckpointError(
      f"{source}: unrecognised checkpoint layout: {plural(len(keys), 'key')}, first "
      f"{keys[:5]!r}, "
      f"top-level names {dict(sorted(tops.items()))}; expected Stereo Any Video keys "
      f"({', '.join(sorted(SAV_TOP_LEVEL))}) or Video Depth Anything keys (pretrained, head)")


KIND_NAMES = {"sav": "a Stereo Any Video", "vda": "a Video Depth Anything (depth prior only)",
              "raft": "a RAFT (optical flow)", "raft_small": "a RAFT-small (optical flow)"}
# What to do with a file of each kind, unless the caller says otherwise.
KIND_HINTS = {
    "raft": "RAFT, the evaluation's optical-flow model, needs no conversion: give the file to "
            "python -m eval as --config.metrics.raft=raft-things.pth (or to "
            "sav_jax.convert.raft.load_raft)",
    "raft_small": "only the large RAFT is supported: raft-things.pth, from the same "
                  "models.zip as raft-small.pth"}


def load_state_dict_of_kind(path, want: str, hints: Mapping[str, str] | None = None,
                            label: str | None = None) -> dict:
  """`load_state_dict(path, opaque_unknown=True)`, refused unless `checkpoint_kind` of it
  is `want`: the weights of a training checkpoint whose optimizer or scheduler state holds
  pickled Python objects are read (the objects are replaced by inert placeholders).

  Args:
    path: the checkpoint file.
    want: "sav", "vda" or "raft".
    hints: what to do instead, by the kind found (appended to the error).
    label: how the error names the file (default: the path).

  Raises:
    CheckpointError: unreadable, unrecognised, or of the other kind ("<label> is a Video
      Depth Anything (depth prior only) checkpoint, not a Stereo Any Video one; <hint>").
  """
  # Weights only: pickled objects beside them (an old OneCycleLR's function, a Lightning
  # callback) become inert placeholders, logged, never imported or run.
  sd = load_state_dict(path, opaque_unknown=True)
  kind = checkpoint_kind(sd, source=str(path))
  if kind != want:
    hint = {**KIND_HINTS, **(hints or {})}.get(kind)
    raise CheckpointError(f"{label or path} is {KIND_NAMES[kind]} checkpoint, not "
                          f"{KIND_NAMES[want]} one" + (f"; {hint}" if hint else ""))
  return sd


def save_state_dict(sd: dict, path, *, overwrite: bool = False) -> pathlib.Path:
  """Writes a flat state dict atomically (temporary file in the same folder + `os.replace`).

  Args:
    sd: `{name: array-like}`; jax arrays are fetched to numpy.
    path: `.safetensors`, `.npz`, or `.pth`/`.pt` (the latter only when torch is installed).
    overwrite: replace an existing file; by default an existing file is an error.

  Returns:
    The path written.

  Raises:
    FileExistsError: `path` exists and `overwrite` is False.
    CheckpointError: unknown suffix, `.pth` without torch, non-string keys, or the file
      could not be written (e.g. the disk is full).
  """
  path = pathlib.Path(path)
  suffix = check_writer(path)
  if not all(isinstance(k, str) for k in sd):
    raise CheckpointError(f"{path}: state dict keys must be strings")
  if path.exists() and not overwrite:
    raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
  arrays = {k: np.asarray(v, order="C") for k, v in sd.items()}  # keeps 0-d arrays 0-d
  path.parent.mkdir(parents=True, exist_ok=True)
  # Created as open() creates files (mode 0o666 less the umask, where mkstemp's are 0o600),
  # under a name no other writer uses.
  tmp = str(path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp")
  try:
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    with os.fdopen(fd, "wb") as fh:
      _WRITERS[suffix](arrays, fh)
      fh.flush()
      os.fsync(fh.fileno())
    os.replace(tmp, path)
  except BaseException as e:
    if os.path.exists(tmp):
      os.unlink(tmp)
    if isinstance(e, OSError):  # named by the destination, not the temporary file
      raise CheckpointError(f"{path}: could not write the file ({e.strerror or e})") from e
    raise
  log.info("wrote %d arrays to %s", len(arrays), path)
  return path


def check_writer(path) -> str:
  """The (lower-case) suffix of a state-dict file `save_state_dict` can write at `path`.

  Raises:
    CheckpointError: an unknown suffix, or one written with torch (`.pth`, `.pt`, `.bin`)
      where torch is not installed.
  """
  path = pathlib.Path(path)
  suffix = path.suffix.lower()
  if suffix not in _WRITERS:
    raise CheckpointError(f"{path}: cannot write {suffix or 'a file without a suffix'!r}; use "
                          ".safetensors, .npz or .pth")
  if _WRITERS[suffix] is _write_torch:
    try:
      import torch  # pylint: disable=import-outside-toplevel,unused-import
    except ImportError:
      raise CheckpointError(f"{path}: writing {suffix} needs torch, which is not installed; "
                            "write .safetensors or .npz instead, or install torch") from None
  return suffix


def _write_safetensors(arrays, fh):
  import safetensors.numpy  # pylint: disable=import-outside-toplevel
  # safetensors' numpy reader has no float8 (it wrote F8 that no reader here could load):
  # float8 is widened to float32, as in .npz; bfloat16 stays bfloat16.
  fh.write(safetensors.numpy.save({k: v.astype(np.float32) if v.dtype.name.startswith("float8")
                                   else v for k, v in arrays.items()}))


def _is_ml_dtype(a: np.ndarray) -> bool:
  """bfloat16, float8, ... (ml_dtypes' types: numpy sees most as opaque void, but some, such
  as float8_e5m2, as kind "f", which np.savez writes as an unreadable '<f1')."""
  return (a.dtype.kind == "V" and a.dtype.names is None) or a.dtype.type.__module__ == "ml_dtypes"


def _write_npz(arrays, fh):
  # numpy has no bfloat16/float8: np.savez would write opaque bytes that read back as void
  np.savez(fh, **{k: v.astype(np.float32) if _is_ml_dtype(v) else v
                  for k, v in arrays.items()})


def _write_torch(arrays, fh):
  import torch  # pylint: disable=import-outside-toplevel

  def tensor(v):
    if not _is_ml_dtype(v):
      return torch.from_numpy(v.copy())
    same = getattr(torch, v.dtype.name, None)  # torch.bfloat16, torch.float8_e4m3fn, ...
    if (v.dtype.name.startswith(("bfloat16", "float8")) and isinstance(same, torch.dtype)
        and same.itemsize == v.dtype.itemsize):
      raw = {1: np.uint8, 2: np.uint16}[v.dtype.itemsize]
      return torch.from_numpy(v.view(raw).copy()).view(same)
    return torch.from_numpy(v.astype(np.float32))

  torch.save({k: tensor(v) for k, v in arrays.items()}, fh)


# The state-dict files `save_state_dict` writes, by suffix.
_WRITERS = {".safetensors": _write_safetensors, ".npz": _write_npz, ".pth": _write_torch,
            ".pt": _write_torch, ".bin": _write_torch}
WRITE_SUFFIXES = tuple(_WRITERS)
