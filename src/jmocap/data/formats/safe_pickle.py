"""Reading pickled ``.npz`` members and plain pickle files without running anything:
:func:`load_npz_pickled`, :func:`load_pickle_file`.

Some formats (VideoPose3D's ``positions_2d``) are an ``.npz`` whose members are arrays of Python
objects, which numpy stores pickled. ``np.load(..., allow_pickle=True)`` would run whatever
callable the pickle names (``os.system``, ``builtins.exec``, ...), so such members are read
here instead:

* the ``.npz`` is opened as a zip; every member's size is checked first
  (:func:`jmocap.data.limits.check_npz_members`) and so is each needed member's ``.npy`` header
  (:func:`jmocap.data.limits.check_npy_header`: the declared array fits ``max_file_bytes``);
* an object-dtype member is unpickled by :class:`RestrictedUnpickler`, whose ``find_class``
  admits only what numpy 1.x and 2.x pickles use to rebuild plain arrays and scalars (each
  behind a wrapper that checks its arguments and the size it would allocate) and refuses
  everything else with a :class:`~jmocap.data.clip.FormatError` naming the file and the field;
* the result is then checked (:func:`plain_data`) to be made only of ``dict``, ``list``,
  ``tuple``, ``str``, ``bytes``, ``int``, ``float``, ``bool``, ``None``, numpy scalars and
  arrays of numbers, booleans or strings (never of objects).

The names numpy pickles use (checked with ``pickletools`` on files written by numpy 1.26 and
2.4 at pickle protocols 0 to 5): ``numpy.core.multiarray._reconstruct`` /
``numpy._core.multiarray._reconstruct``, ``numpy.ndarray``, ``numpy.dtype``,
``numpy.core.multiarray.scalar`` / ``numpy._core.multiarray.scalar``,
``numpy.core.numeric._frombuffer`` / ``numpy._core.numeric._frombuffer`` (protocol 5), and for
``bytes`` at protocols 0-2 ``_codecs.encode`` and ``__builtin__.bytes`` (Python 2 names).
"""

from __future__ import annotations

import math
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import FormatError
from jmocap.data.limits import (
    LimitError,
    check_file_size,
    check_npy_header,
    check_npz_members,
    current,
)

# numpy's own reconstructors, found through public objects (their module moved in numpy 2)
_NP_RECONSTRUCT = np.ndarray.__reduce__(np.zeros(0))[0]
_NP_SCALAR = np.float64(0).__reduce__()[0]

# dtype kinds an array or scalar read from a pickle may have: booleans, numbers, strings
_PLAIN_KINDS = "biufcUS"
# nesting of dicts / lists / tuples a pickled value may have
MAX_PICKLE_DEPTH = 100

_REFUSAL = "(only arrays, dicts, lists, strings and numbers are read)"


class _Refused(Exception):
    """A pickle asked for something not admitted (turned into a FormatError by the loader)."""


class _TooBig(_Refused):
    """An array over ``max_file_bytes`` (turned into a LimitError)."""


class _NDArrayClass:
    """Stands for ``numpy.ndarray`` in a pickle: only :func:`_reconstruct` accepts it (calling
    it, or building an instance of it, fails)."""

    __slots__ = ()


_NDARRAY = _NDArrayClass()


class _ArrayBuilder:
    """What :func:`_reconstruct` returns: the pickle's ``BUILD`` calls :meth:`__setstate__`
    with numpy's array state, which is checked (shape, dtype, data length, size within
    ``max_file_bytes``) before numpy builds the array (numpy would allocate the declared shape
    before looking at the data)."""

    __slots__ = ("array",)

    def __init__(self):
        self.array: np.ndarray | None = None

    def __setstate__(self, state):
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _Refused(f"array state is not numpy's (a {type(state).__name__})")
        shape, dtype, fortran, data = state[-4:]
        if not (isinstance(shape, tuple) and all(type(n) is int and n >= 0 for n in shape)):
            raise _Refused(f"array shape {shape!r} is not a tuple of non-negative integers")
        if not isinstance(dtype, np.dtype):
            raise _Refused(f"array dtype is a {type(dtype).__name__}, not a numpy dtype")
        if not isinstance(fortran, (bool, int)):
            raise _Refused("array order flag is not a boolean")
        n = math.prod(shape)
        _check_alloc(n * dtype.itemsize)
        if dtype.hasobject:
            if dtype != np.dtype(object):
                raise _Refused(f"structured dtype with objects {dtype}")
            if not isinstance(data, list) or len(data) != n:
                raise _Refused("object array data is not a list of its size")
        else:
            if isinstance(data, str):
                # a Python 2 pickle's 8-bit string, decoded as latin-1 by the unpickler: its
                # characters are the bytes (numpy's own __setstate__ accepts it the same way)
                try:
                    data = data.encode("latin-1")
                except UnicodeEncodeError:
                    raise _Refused("array data is a text string, not bytes") from None
                state = state[:-1] + (data,)
            if not isinstance(data, (bytes, bytearray)) or len(data) != n * dtype.itemsize:
                raise _Refused(f"array data is not {n * dtype.itemsize} bytes")
        a = _NP_RECONSTRUCT(np.ndarray, (0,), b"b")
        a.__setstate__(state)
        self.array = a


def _check_alloc(nbytes: int) -> None:
    lim = current().max_file_bytes
    if nbytes > lim:
        raise _TooBig(
            f"an array of {nbytes} bytes, over the limit max_file_bytes = {lim} "
            f"(--limit max_file_bytes=...)"
        )


def _reconstruct(subtype, shape, typecode):
    """``numpy.core.multiarray._reconstruct``: only plain ``ndarray``; returns an
    :class:`_ArrayBuilder` that the pickle's ``BUILD`` fills."""
    if subtype is not _NDARRAY:
        raise _Refused(f"rebuilding an array of class {type(subtype).__name__}")
    return _ArrayBuilder()


def _dtype(spec, align=False, copy=False):
    """``numpy.dtype``: from a type string only (``'f4'``, ``'O8'``, ``'V16'``, ...)."""
    if not isinstance(spec, str):
        raise _Refused(f"a dtype from a {type(spec).__name__}")
    return np.dtype(spec, bool(align), bool(copy))


def _scalar(dtype, *args):
    """``numpy.core.multiarray.scalar``: a numpy scalar from its dtype and bytes."""
    if not isinstance(dtype, np.dtype) or (dtype.hasobject and dtype != np.dtype(object)):
        raise _Refused(f"a scalar of dtype {dtype!r}")
    if args and not dtype.hasobject and not isinstance(args[0], (bytes, bytearray)):
        raise _Refused("scalar data is not bytes")
    return _NP_SCALAR(dtype, *args)


def _frombuffer(buf, dtype, shape, order):
    """``numpy.core.numeric._frombuffer`` (pickle protocol 5): an array over in-band bytes."""
    if not isinstance(dtype, np.dtype) or dtype.hasobject:
        raise _Refused(f"an array of dtype {dtype!r} from a buffer")
    if not isinstance(buf, (bytes, bytearray, pickle.PickleBuffer)):
        raise _Refused(f"array data is a {type(buf).__name__}")
    if order not in ("C", "F"):
        raise _Refused(f"array order {order!r}")
    return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order)


def _codecs_encode(text, encoding="utf-8", *rest):
    """``_codecs.encode`` as protocols 0-2 use it for ``bytes``: a str in latin-1, nothing else."""
    if rest or not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise _Refused(f"_codecs.encode with encoding {encoding!r}")
    return text.encode("latin-1")


def _empty_bytes(*args):
    """``bytes()`` as protocols 0-2 write ``b''`` (no arguments: ``bytes(n)`` would allocate)."""
    if args:
        raise _Refused("bytes() with arguments")
    return b""


_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy.core.multiarray", "scalar"): _scalar,
    ("numpy._core.multiarray", "scalar"): _scalar,
    ("numpy.core.numeric", "_frombuffer"): _frombuffer,
    ("numpy._core.numeric", "_frombuffer"): _frombuffer,
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _dtype,
    ("_codecs", "encode"): _codecs_encode,
    ("__builtin__", "bytes"): _empty_bytes,
    ("builtins", "bytes"): _empty_bytes,
}


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that rebuilds numpy arrays, numpy scalars and Python's plain types only.

    ``find_class`` returns checked stand-ins for the names numpy's pickles use (see the module
    docstring) and raises :class:`FormatError` ``"<where>: field 'x': refuses to unpickle
    'module.name' (...)"`` for anything else; persistent ids are refused too. A stand-in that
    is misused raises an internal error the loader reports the same way.
    """

    def __init__(self, file, where: str, field: str):
        # latin-1: Python 2's 8-bit strings (and numpy arrays pickled by Python 2) as numpy reads them
        super().__init__(file, fix_imports=True, encoding="latin1")
        self.where, self.field = where, field

    def find_class(self, module, name):
        found = _ALLOWED.get((module, name))
        if found is None:
            module = "builtins" if module == "__builtin__" else module  # protocols 0-2 say so
            raise FormatError(
                f"{self.where}: field {self.field!r}: refuses to unpickle {module + '.' + name!r} "
                f"{_REFUSAL}"
            )
        return found

    def persistent_load(self, pid):
        raise FormatError(
            f"{self.where}: field {self.field!r}: refuses a pickled persistent id {_REFUSAL}"
        )


def plain_data(obj: Any, where: str, field: str) -> Any:
    """``obj`` (what :class:`RestrictedUnpickler` returned) checked to be plain data.

    Admitted: ``dict`` (keys ``str``, ``bytes``, ``int``, ``float``, ``bool``, ``None`` or numpy
    scalars), ``list``, ``tuple``, ``str``, ``bytes``, ``int``, ``float``, ``bool``, ``None``,
    numpy scalars and arrays whose dtype is boolean, numeric or string (kinds ``biufcUS``);
    nesting at most :data:`MAX_PICKLE_DEPTH` deep, no container that contains itself. Containers
    are copied (shared ones once); the arrays the unpickler built replace their builders.
    Anything else: :class:`FormatError` naming ``where``, ``field`` and the path inside it.
    """
    done: dict[int, Any] = {}
    busy: set[int] = set()

    def fail(at: str, msg: str, refusal: bool = True):
        if len(at) > 80:
            at = at[:80] + "..."
        place = f" at {at}" if at else ""
        return FormatError(f"{where}: field {field!r}: {msg}{place}" + (f" {_REFUSAL}" if refusal else ""))

    def walk(x, at: str, depth: int):
        if x is None or isinstance(x, (str, bytes, int, float)):  # bool is an int
            return x
        if isinstance(x, _ArrayBuilder):
            if x.array is None:
                raise fail(at, "an array without its data")
            x = x.array
        if isinstance(x, (np.ndarray, np.generic)):
            if x.dtype.kind not in _PLAIN_KINDS:
                what = "Python objects" if x.dtype.hasobject else f"dtype {x.dtype}"
                raise fail(at, f"holds an array of {what}")
            return x
        if not isinstance(x, (dict, list, tuple)):
            raise fail(at, f"holds a {type(x).__name__}")
        if id(x) in done:
            return done[id(x)]
        if id(x) in busy:
            raise fail(at, "contains itself", refusal=False)
        if depth >= MAX_PICKLE_DEPTH:
            raise fail(at, f"nests deeper than {MAX_PICKLE_DEPTH} levels", refusal=False)
        busy.add(id(x))
        if isinstance(x, dict):
            out: Any = {}
            for k, v in x.items():
                if not (k is None or isinstance(k, (str, bytes, int, float, np.generic))):
                    raise fail(at, f"has a dict key of type {type(k).__name__}")
                if isinstance(k, np.generic) and k.dtype.kind not in _PLAIN_KINDS:
                    raise fail(at, f"has a dict key of dtype {k.dtype}")
                out[k] = walk(v, f"{at}[{k!r}]", depth + 1)
        else:
            items = [walk(v, f"{at}[{i}]", depth + 1) for i, v in enumerate(x)]
            out = items if isinstance(x, list) else tuple(items)
        busy.discard(id(x))
        done[id(x)] = out
        return out

    return walk(obj, "", 0)


def _restricted_load(f, where: str, field: str, malformed: str, one_line: bool = False) -> Any:
    """``RestrictedUnpickler(f, where, field).load()`` with its failures as jmocap's errors: a
    refused callable or class a :class:`FormatError`, an allocation over the limits a
    :class:`LimitError`, and any other error of a truncated or malformed pickle (any error of a
    stand-in) a :class:`FormatError` ``"<malformed> (<error>)"`` (``one_line``: its whitespace
    collapsed)."""
    try:
        return RestrictedUnpickler(f, where, field).load()
    except FormatError:
        raise
    except _TooBig as e:
        raise LimitError(f"{where}: field {field!r}: {e}") from None
    except _Refused as e:
        raise FormatError(f"{where}: field {field!r}: refuses {e} {_REFUSAL}") from None
    except Exception as e:  # truncated or malformed pickle: any error of a stand-in
        text = " ".join(str(e).split()) if one_line else str(e)
        raise FormatError(f"{malformed} ({text})") from None


def _unpickle_member(z: zipfile.ZipFile, info: zipfile.ZipInfo, where: str, field: str) -> Any:
    """One ``.npy`` member: a plain array as numpy reads it without pickle, or an object array
    through :class:`RestrictedUnpickler` and :func:`plain_data` (a 0-d one gives its item)."""
    with z.open(info) as f:
        shape, _fortran, dtype = check_npy_header(f, where, field)
        if dtype.hasobject:
            top = _restricted_load(f, where, field, f"{where}: field {field!r}: not a readable pickled array")
            if isinstance(top, _ArrayBuilder) and top.array is not None:
                arr = top.array
                if arr.shape != shape:
                    raise FormatError(
                        f"{where}: field {field!r}: pickled array has shape {arr.shape}, "
                        f"the header says {shape}"
                    )
                if arr.dtype.hasobject:
                    top = arr.item() if arr.ndim == 0 else arr.tolist()
            return plain_data(top, where, field)
    with z.open(info) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def load_npz_pickled(
    path: str | os.PathLike, fields: tuple[str, ...] | list[str], where: str | None = None
) -> dict[str, Any]:
    """The members ``fields`` of an ``.npz`` that may hold pickled objects, read safely.

    Checks, in order: the file size (:func:`~jmocap.data.limits.check_file_size`), every
    member's decompressed size (:func:`~jmocap.data.limits.check_npz_members`), each needed
    member's ``.npy`` header (:func:`~jmocap.data.limits.check_npy_header`). A plain member is
    read as numpy reads it without pickle; an object-dtype one is unpickled by
    :class:`RestrictedUnpickler` and checked by :func:`plain_data` (a 0-d object array, as
    ``np.save`` writes a dict, gives the dict itself). Members not in ``fields`` are not read.
    Returns ``{field: value}`` for the fields present. Raises :class:`FormatError` (or
    :class:`~jmocap.data.limits.LimitError`) naming the file and the field; a file that is not
    a zip raises ``zipfile.BadZipFile``, for the caller's format error.
    """
    where = where or str(path)
    check_file_size(path, where)
    out: dict[str, Any] = {}
    with open(Path(path), "rb") as fh, zipfile.ZipFile(fh) as z:
        check_npz_members(z, where)
        members = {i.filename.removesuffix(".npy"): i for i in z.infolist()}
        for field in fields:
            if field in members:
                out[field] = _unpickle_member(z, members[field], where, field)
    return out


def load_pickle_file(path: str | os.PathLike, where: str | None = None, field: str = "pickle") -> Any:
    """The value of a plain pickle file (not an ``.npz``), read safely: the file's size is checked
    (:func:`~jmocap.data.limits.check_file_size`), it is unpickled by :class:`RestrictedUnpickler`
    (numpy arrays and scalars, dicts, lists, strings and numbers only; Python 2 pickles too, their
    8-bit strings read as latin-1, as ``pickle.load(f, encoding="latin1")`` does) and checked by
    :func:`plain_data`. Anything else is a :class:`FormatError` naming the file (and ``field``),
    before any of it could run; an array over ``max_file_bytes`` a
    :class:`~jmocap.data.limits.LimitError`. Used for DIP-IMU's per-sequence pickles."""
    where = where or str(path)
    check_file_size(path, where)
    with open(Path(path), "rb") as f:
        top = _restricted_load(f, where, field, f"{where}: not a readable pickle file", one_line=True)
    return plain_data(top, where, field)


__all__ = [
    "MAX_PICKLE_DEPTH",
    "RestrictedUnpickler",
    "load_npz_pickled",
    "load_pickle_file",
    "plain_data",
]
